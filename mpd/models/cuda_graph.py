"""A diffusion training step captured in a CUDA graph: the whole step replayed as one launch.

On a GPU the training step of the priors' networks (a few thousand small kernels: the U-Net's forward and backward,
gradient clipping, AdamW, the EMA) is bound by kernel launches, not by arithmetic: its rate on a large GPU is the
same at batch 512, 1024 and 2048 (benchmarks/results/2026-12-04-h200-gpu-check.json). Captured once, the step replays
without a launch per kernel. What the step computes is unchanged (the same batch draw, loss, clipping, fused AdamW
and EMA, in the same order, from the same seeded generator), so it is an execution mode, not part of a model's
identity; the values that change from step to step (learning rate, EMA weight) are device tensors written before
each replay.

Only the diffusion loss is captured (the CVAE's KL warm-up weight is a Python float of its loss) and only on CUDA
(``train_model(cuda_graph=...)``; ``MPD_CUDA_GRAPH=0`` turns it off). The step's body is the eager step's
(:class:`mpd.models.step.StepBody`).
"""

from __future__ import annotations

from typing import Any

import torch

from mpd.device import resolve
from mpd.models.step import StepBody, ema_weight

__all__ = ["EAGER_STEPS", "GraphedStep", "ema_weight", "graph_supported"]

EAGER_STEPS = 3  # steps run eagerly (on a side stream) before the capture: the optimizer's state, cached tables


def graph_supported(kind: str, device: torch.device) -> bool:
    """Whether a training of ``kind`` on ``device`` is captured by default."""
    return kind == "diffusion" and resolve(device).cuda_graph


class GraphedStep(StepBody):
    """The step body captured: ``step(s, lr)`` for 0-based step ``s``: the first :data:`EAGER_STEPS` calls run it
    eagerly, the next one captures it and replays it, every later one replays it. The batch draw and the running
    sum are inside the capture, the learning rate and the EMA's weight (:func:`mpd.models.step.ema_weight`) are
    device tensors written before each replay. ``running`` (a 0-d device tensor) accumulates the loss in place;
    reset it with ``running.zero_()``, never by assignment."""

    autocast_cache = False  # autocast's weight cache would hold casts of the captured step's weights

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        device = self.running.device
        self.lr = torch.tensor(float(self.ts.lr), device=device)
        self.ema_weight_t = torch.zeros((), device=device)
        for g in self.opt.param_groups:  # read from device memory at every replay
            g["lr"] = self.lr
            g["capturable"] = True
        self.eager_left = EAGER_STEPS
        self.graph: torch.cuda.CUDAGraph | None = None

    def ema_w(self, step: int) -> torch.Tensor:
        return self.ema_weight_t

    def _captured(self) -> None:
        xb, cb = self.draw()
        loss = self.body(xb, cb, -1)  # the step's number reaches the body through the device tensors only
        with torch.no_grad():
            self.running.add_(loss)

    def __call__(self, step: int, lr: float) -> None:
        self.lr.fill_(lr)
        self.ema_weight_t.fill_(ema_weight(self.ts, step))
        if self.graph is not None:
            self.graph.replay()
            return
        if self.eager_left > 0:  # eager steps on a side stream, as a capture needs (allocator, lazy initialisations)
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                self.opt.zero_grad(set_to_none=True)
                self._captured()
            torch.cuda.current_stream().wait_stream(side)
            self.eager_left -= 1
            return
        self.opt.zero_grad(set_to_none=True)  # the captured backward writes the gradients (no accumulation)
        graph = torch.cuda.CUDAGraph()
        graph.register_generator_state(self.gen)
        with torch.cuda.graph(graph):
            self._captured()
        self.graph = graph
        graph.replay()  # the capture records the step without running it
