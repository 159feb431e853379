"""A diffusion training step captured in a CUDA graph: the whole step replayed as one launch.

On a GPU the training step of the priors' networks (a few thousand small kernels: the U-Net's forward and backward,
gradient clipping, AdamW, the EMA) is bound by kernel launches, not by arithmetic: its rate on a large GPU is the
same at batch 512, 1024 and 2048 (benchmarks/results/2026-12-04-h200-gpu-check.json). Captured once, the step replays
without a launch per kernel. What the step computes is unchanged (the same batch draw, loss, clipping, fused AdamW
and EMA, in the same order, from the same seeded generator), so it is an execution mode, not part of a model's
identity; the values that change from step to step (learning rate, EMA weight) are device tensors written before
each replay.

Only the diffusion loss is captured (the CVAE's KL warm-up weight is a Python float of its loss) and only on CUDA
(``train_model(cuda_graph=...)``; ``MPD_CUDA_GRAPH=0`` turns it off).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import torch
from torch import nn

from mpd.tasks.spec import TrainingSpec

EAGER_STEPS = 3  # steps run eagerly (on a side stream) before the capture: the optimizer's state, cached tables


def graph_supported(kind: str, device: torch.device) -> bool:
    """Whether a training of ``kind`` on ``device`` is captured by default."""
    return (
        kind == "diffusion"
        and device.type == "cuda"
        and os.environ.get("MPD_CUDA_GRAPH", "1") != "0"
        and hasattr(torch.cuda.CUDAGraph, "register_generator_state")
    )


def ema_weight(ts: TrainingSpec, step: int) -> float:
    """The EMA's interpolation weight after (0-based) step ``step``: 1 (a copy of the weights) before ``ema_start``,
    ``1 - ema_decay`` on an EMA step, 0 (unchanged) between EMA steps -- the eager loop's rule as one lerp."""
    done = step + 1
    if done % ts.ema_every:
        return 0.0
    return 1.0 if done < ts.ema_start else 1.0 - ts.ema_decay


class GraphedStep:
    """Call ``step(s, lr)`` for 0-based step ``s``: the first :data:`EAGER_STEPS` calls run eagerly, the next one
    captures the step and replays it, every later one replays it. ``running`` (a 0-d device tensor) accumulates
    the loss in place; reset it with ``running.zero_()``, never by assignment."""

    def __init__(
        self,
        net: nn.Module,
        ema: nn.Module,
        opt: torch.optim.Optimizer,
        draw: Callable[[], tuple[torch.Tensor, dict[str, torch.Tensor]]],
        gen: torch.Generator,
        ts: TrainingSpec,
        loss_kwargs: dict,
        bf16: bool,
        running: torch.Tensor,
    ):
        device = running.device
        self.net, self.ema, self.opt, self.draw, self.gen, self.ts = net, ema, opt, draw, gen, ts
        self.loss_kwargs, self.bf16, self.running = loss_kwargs, bf16, running
        self.lr = torch.tensor(float(ts.lr), device=device)
        self.ema_w = torch.zeros((), device=device)
        for g in opt.param_groups:  # read from device memory at every replay
            g["lr"] = self.lr
            g["capturable"] = True
        self.eager_left = EAGER_STEPS
        self.graph: torch.cuda.CUDAGraph | None = None
        self.ema_pairs = list(zip(ema.parameters(), net.parameters()))

    def _body(self) -> None:
        xb, cb = self.draw()
        # autocast's weight cache must be off inside a capture (it would hold casts of the captured step's weights)
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.bf16, cache_enabled=False):
            loss = self.net.loss(xb, cb, self.gen, **self.loss_kwargs)
        loss.backward()
        if self.ts.grad_clip_norm > 0:
            nn.utils.clip_grad_norm_(self.net.parameters(), self.ts.grad_clip_norm)
        self.opt.step()
        with torch.no_grad():
            for pe, pm in self.ema_pairs:
                pe.lerp_(pm, self.ema_w)
            self.running.add_(loss.detach())

    def __call__(self, step: int, lr: float) -> None:
        self.lr.fill_(lr)
        self.ema_w.fill_(ema_weight(self.ts, step))
        if self.graph is not None:
            self.graph.replay()
            return
        if self.eager_left > 0:  # eager steps on a side stream, as a capture needs (allocator, lazy initialisations)
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                self.opt.zero_grad(set_to_none=True)
                self._body()
            torch.cuda.current_stream().wait_stream(side)
            self.eager_left -= 1
            return
        self.opt.zero_grad(set_to_none=True)  # the captured backward writes the gradients (no accumulation)
        graph = torch.cuda.CUDAGraph()
        graph.register_generator_state(self.gen)
        with torch.cuda.graph(graph):
            self._body()
        self.graph = graph
        graph.replay()  # the capture records the step without running it
