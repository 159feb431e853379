"""The body of the velocity and acceleration costs: a per-point penalty on a phase derivative, integrated."""

from __future__ import annotations

import torch

# Added under the square root of the official norm form, sqrt(|x|^2 + eta): the norm has no gradient at x = 0,
# where every clamped B-spline starts and ends; with eta the gradient there is 0 and elsewhere changes by a
# relative O(eta / |x|^2). Value and gradient use the same expression.
NORM_EPS = 1e-12


def derivative_penalty(x: torch.Tensor, w: torch.Tensor, weight: float, squared: bool):
    """Cost (B,) = sum_i w_i c(x_i) and its weighted gradient (B, n, dof), for x (B, n, dof).

    ``squared``: c = |x|^2 / 2 (the paper); otherwise c = sqrt(|x|^2 + eta) / 2 (the authors' configs).
    """
    sq = x.square().sum(-1)  # (B, n)
    if squared:
        return (0.5 * sq * w).sum(-1), x * (weight * w)[:, None]
    nrm = (sq + NORM_EPS).sqrt()
    return (0.5 * nrm * w).sum(-1), x * ((0.5 * weight) * w / nrm)[..., None]
