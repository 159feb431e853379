"""A diffusion training step on a CPU with the loss's forward and backward compiled by torch.compile (inductor).

The eager step of the priors' networks spends about a third of its time outside the convolutions, in a few hundred
small kernels (Mish and GroupNorm forward and backward, FiLM, residual sums, casts) each of which reads and writes
the whole activation; inductor fuses them into a few C++ loops, and the convolutions stay oneDNN's. Only the loss's
deterministic part is compiled (:meth:`DiffusionModel.loss_of_draws`): the batch, the diffusion steps and the
noise are drawn eagerly from the training's generator in the eager loop's order, and the gradient clipping, fused
AdamW and the EMA are the eager step's own (:meth:`mpd.models.step.StepBody.body`). So it computes what the
eager step computes, in the same arithmetic (fp32, or bf16 autocast where the training's precision asks for it),
up to float rounding inside the fused kernels: an execution mode, not part of a model's identity, recorded in the
checkpoint and the meta (``execution``).

Where: a diffusion training on a CPU with a C++ compiler, for runs of at least :data:`MIN_STEPS` steps in one call
(compiling costs 10-200 s on a 2-core CPU, a few hundred steps' worth). ``MPD_TRAIN_COMPILE=0`` turns it off,
``MPD_TRAIN_COMPILE=1`` turns it on for any run length; ``train_model(compile_step=...)`` decides per call.
"""

from __future__ import annotations

import os
import shutil
import sys
from typing import Any

import torch

from mpd.models.step import EagerStep

ENV = "MPD_TRAIN_COMPILE"
MIN_STEPS = 2000  # steps in one call from which the compiled step is the default (MPD_TRAIN_COMPILE unset)
# Inductor's C++ wrapper: the compiled graphs call their kernels from C++ instead of a Python function, which saves
# the Python overhead of the ~100 kernel launches of a step (Zen 4, 1 thread: +5 % steps/s on the 2-D net, +6 % on
# the Panda net; the same kernels, so the same numbers; benchmarks/test_bench_training.py). It compiles longer the
# first time (2-D net 10 s, Panda net ~160 s on 2 cores), which the MIN_STEPS default covers.
INDUCTOR_OPTIONS = {"cpp_wrapper": True}


def cxx_available() -> bool:
    """Whether inductor finds a C++ compiler (``CXX``, else g++ or c++ on the PATH)."""
    return any(shutil.which(c) for c in (os.environ.get("CXX", ""), "g++", "c++") if c)


def compile_supported(kind: str, device: torch.device) -> bool:
    """Whether a training of ``kind`` on ``device`` can run the compiled step at all."""
    return kind == "diffusion" and torch.device(device).type == "cpu" and cxx_available()


def compile_by_default(kind: str, device: torch.device, n_steps: int) -> bool:
    """Whether a call that trains ``n_steps`` steps runs the compiled step when not told (see the module docstring)."""
    env = os.environ.get(ENV, "")
    if env == "0" or not compile_supported(kind, device):
        return False
    return env == "1" or n_steps >= MIN_STEPS


class CompiledStep(EagerStep):
    """The eager step with the loss's forward and backward compiled: the diffusion steps and the noise are drawn
    eagerly (:meth:`DiffusionModel.loss_draws`), their loss (:meth:`DiffusionModel.loss_of_draws`) is compiled; the
    rest of the body (clipping, AdamW, EMA) is the eager step's. ``inductor_options`` replaces
    :data:`INDUCTOR_OPTIONS` (benchmarks compare them). Should the compilation fail (no working C++
    compiler), the step says so once and goes on eagerly with the same draws (``self.compiled`` False)."""

    def __init__(self, *args: Any, inductor_options: dict[str, Any] | None = None, **kwargs: Any):
        super().__init__(*args, **kwargs)
        kw = dict(self.loss_kwargs)
        self.draw_kwargs = {"t_grid": kw.pop("t_grid", None), "t_grid_fraction": kw.pop("t_grid_fraction", 0.0)}
        self.loss_kwargs = kw
        self.compiled = True
        options = INDUCTOR_OPTIONS if inductor_options is None else inductor_options
        self._loss_fn = torch.compile(self._loss, dynamic=False, options=options)

    def _loss(self, x0: torch.Tensor, context: dict[str, torch.Tensor], t: torch.Tensor, noise: torch.Tensor):
        with self.autocast():
            return self.net.loss_of_draws(x0, context, t, noise, **self.loss_kwargs)

    def loss(self, xb: torch.Tensor, cb: dict[str, torch.Tensor], step: int) -> torch.Tensor:
        t, noise = self.net.loss_draws(xb, self.gen, **self.draw_kwargs)
        if self.shard is not None:  # this rank's rows of the whole batch's draws (mpd.models.data_parallel)
            xb, cb, t, noise = self.shard.take(xb, cb, t, noise)
        if self.compiled:
            try:
                return self._loss_fn(xb, cb, t, noise)
            except torch._dynamo.exc.BackendCompilerFailed as e:
                print(f"mpd: the compiled training step failed to compile ({e}); training eagerly", file=sys.stderr)
                self.compiled = False
        return self._loss(xb, cb, t, noise)
