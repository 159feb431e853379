"""The training step: one body (loss, backward, gradient clipping, AdamW, EMA) and the ways it is executed.

A step object is called as ``step(s, lr)`` for (0-based) step ``s`` at learning rate ``lr``: it draws its batch
from the training's generator, runs the body and adds the detached loss to the running sum (a 0-d tensor, reset
in place by the loop). :class:`EagerStep` runs the body eagerly and is the reference;
:class:`mpd.models.compiled_step.CompiledStep` compiles its loss (CPU), :class:`mpd.models.cuda_graph.GraphedStep`
captures the whole step in a CUDA graph. All three run :meth:`StepBody.body` and the EMA rule of
:func:`ema_weight` / :func:`apply_ema`, so they compute the same step in the same order from the same draws.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable
from typing import Any, Protocol

import torch
from torch import nn

from mpd.device import Arithmetic
from mpd.models.data_parallel import Shard
from mpd.tasks.spec import TrainingSpec

Batch = tuple[torch.Tensor, dict[str, torch.Tensor]]


class TrainingStep(Protocol):
    """What the training loop calls: run (0-based) step ``step`` at ``lr``, adding its loss to the running sum."""

    def __call__(self, step: int, lr: float) -> None: ...


def ema_weight(ts: TrainingSpec, step: int) -> float:
    """The EMA's interpolation weight after (0-based) step ``step``: 1 (a copy of the weights) before ``ema_start``,
    ``1 - ema_decay`` on an EMA step (every ``ema_every`` steps), 0 (unchanged) between EMA steps."""
    done = step + 1
    if done % ts.ema_every:
        return 0.0
    return 1.0 if done < ts.ema_start else 1.0 - ts.ema_decay


@torch.no_grad()
def apply_ema(ema_params: Iterable[torch.Tensor], params: Iterable[torch.Tensor], w: float | torch.Tensor) -> None:
    """Move the EMA's weights ``w`` of the way to the weights: a copy for 1, nothing for 0, a lerp otherwise. A
    tensor ``w`` (a captured step's, written before each replay) is always one lerp, whatever its value."""
    ema_params, params = list(ema_params), list(params)
    if isinstance(w, torch.Tensor):
        for pe, pm in zip(ema_params, params):
            pe.lerp_(pm, w)
    elif w == 1.0:
        torch._foreach_copy_(ema_params, params)
    elif w != 0.0:
        torch._foreach_lerp_(ema_params, params, w)


class StepBody:
    """The state a step works on and the body every execution mode runs: loss (in the ``arithmetic`` of
    :func:`mpd.device.resolve`), backward, gradient clipping, AdamW, EMA. ``draw()`` gives the next batch;
    ``running`` is the 0-d loss sum. ``shard``: this rank's rows of each batch and the ranks' gradient averaging, in a
    data-parallel training (:mod:`mpd.models.data_parallel`); the loss it returns is then the ranks' mean."""

    autocast_cache = True  # autocast's weight cache (a captured step turns it off)

    def __init__(
        self,
        kind: str,
        net: nn.Module,
        ema: nn.Module,
        opt: torch.optim.Optimizer,
        gen: torch.Generator,
        ts: TrainingSpec,
        loss_kwargs: dict[str, Any],
        arithmetic: Arithmetic,
        draw: Callable[[], Batch] | None = None,
        running: torch.Tensor | None = None,
        shard: Shard | None = None,
    ):
        self.kind, self.net, self.ema, self.opt, self.gen, self.ts = kind, net, ema, opt, gen, ts
        self.loss_kwargs, self.arithmetic, self.draw, self.running = loss_kwargs, arithmetic, draw, running
        self.shard = shard
        self.params = list(net.parameters())
        self.ema_params = list(ema.parameters())

    def autocast(self) -> contextlib.AbstractContextManager:
        return self.arithmetic.autocast(cache_enabled=self.autocast_cache)

    def loss(self, xb: torch.Tensor, cb: dict[str, torch.Tensor], step: int) -> torch.Tensor:
        if self.kind == "cvae" and self.ts.kl_warmup_steps > 0:
            self.loss_kwargs["kl_scale"] = min(1.0, step / self.ts.kl_warmup_steps)
        if self.shard is not None:  # the whole batch's draws, then this rank's rows (mpd.models.data_parallel)
            kw = dict(self.loss_kwargs)
            t, noise = self.net.loss_draws(xb, self.gen, kw.pop("t_grid", None), kw.pop("t_grid_fraction", 0.0))
            xb, cb, t, noise = self.shard.take(xb, cb, t, noise)
            with self.autocast():
                return self.net.loss_of_draws(xb, cb, t, noise, **kw)
        with self.autocast():
            return self.net.loss(xb, cb, self.gen, **self.loss_kwargs)

    def ema_w(self, step: int) -> float | torch.Tensor:
        return ema_weight(self.ts, step)

    def body(self, xb: torch.Tensor, cb: dict[str, torch.Tensor], step: int) -> torch.Tensor:
        """Step ``step`` on the batch ``(xb, cb)`` from zeroed gradients at the optimizer's set learning rate;
        returns the detached loss."""
        loss = self.loss(xb, cb, step)
        loss.backward()
        loss = self.shard.average(loss) if self.shard is not None else loss.detach()
        if self.ts.grad_clip_norm > 0:
            nn.utils.clip_grad_norm_(self.params, self.ts.grad_clip_norm)
        self.opt.step()
        apply_ema(self.ema_params, self.params, self.ema_w(step))
        return loss


class EagerStep(StepBody):
    """The body run eagerly: the reference of the other execution modes. ``on_batch(xb, cb, s, lr)`` runs step
    ``s`` on a given batch and returns its loss (for benchmarks); calling it draws the batch and sums the loss."""

    def on_batch(self, xb: torch.Tensor, cb: dict[str, torch.Tensor], step: int, lr: float) -> torch.Tensor:
        self.opt.zero_grad(set_to_none=True)
        for g in self.opt.param_groups:
            g["lr"] = lr
        return self.body(xb, cb, step)

    def __call__(self, step: int, lr: float) -> None:
        xb, cb = self.draw()
        self.running.add_(self.on_batch(xb, cb, step, lr))
