"""Projected gradient descent on unit-normalized free control points: the routine shared by MPD's guidance and
every "+Cost" baseline (same step count, step size, clipping and maximum deviation for all of them)."""

from __future__ import annotations

from collections.abc import Callable

import torch


def clip_grad(g: torch.Tensor, clip: float | None) -> torch.Tensor:
    """Element-wise value clipping (the authors' ``clip_grad_rule: value``); ``None`` leaves g unchanged."""
    return g if clip is None else g.clamp(-clip, clip)


def project(x: torch.Tensor, anchor: torch.Tensor, max_perturb: float) -> torch.Tensor:
    """Keep every entry of x within +-max_perturb of the anchor (the paper's delta)."""
    return anchor + (x - anchor).clamp(-max_perturb, max_perturb)


def optimize(
    x0: torch.Tensor,
    grad_fn: Callable[[torch.Tensor], torch.Tensor],
    steps: int,
    lr: float,
    max_perturb: float,
    grad_clip: float | None,
    callback: Callable[[int, torch.Tensor], None] | None = None,
) -> torch.Tensor:
    """x_{k+1} = x0 + clip(x_k - lr * clip(grad C(x_k)) - x0, -delta, delta), for ``steps`` steps."""
    x = x0
    for k in range(steps):
        x = project(x - lr * clip_grad(grad_fn(x), grad_clip), x0, max_perturb)
        if callback is not None:
            callback(k, x)
    return x
