"""Shared step of the "[Prior]+Cost" baselines: sample from a prior, then optimize the cost from the samples with
the routine and step count shared by every "+Cost" baseline (``opt_steps`` steps, ``opt_lr``, ``opt_max_perturb``,
``opt_grad_clip``)."""

from __future__ import annotations

import torch

from mpd.planners.base import Context, HistoryStep, Planner, Timer
from mpd.planners.optimize import optimize


def optimize_samples(planner: Planner, x: torch.Tensor, ctx: Context, timer: Timer, hist: list | None) -> torch.Tensor:
    s = planner.settings
    start = len(hist) if hist is not None else 0

    def cb(k: int, xk: torch.Tensor) -> None:
        if hist is not None:
            hist.append(HistoryStep("optimization", start + k, planner.normalizer.unnormalize(xk)))

    return optimize(x, planner.cost_grad_fn(ctx, timer), s.opt_steps, s.opt_lr, s.opt_max_perturb, s.opt_grad_clip, cb)
