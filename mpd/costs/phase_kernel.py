"""Compiled fast path of the per-point phase costs on the CPU: velocity, acceleration and joint limits in one pass.

Each of these costs is a few elementwise operations on the dense (B, n, dof) trajectory fields, a dozen torch
kernels each (square, sum, sqrt, the quadrature weights, the gradient's scaling, ...), whose time on a CPU is
nearly all per-kernel overhead. This pass (numba, ``cache=True``)
reads the stacked fields (B, 3, n, dof) (q, q', q'', :attr:`mpd.trajectory.Dense.stacked`) once and writes each
cost's value and the weighted sum of their gradients into one (B, 3, n, dof) buffer, the layout the chain rule
reads (:meth:`mpd.trajectory.LinearTrajectory.grad_to_free_stacked`), in the fields' memory layout.

The costs say what they ask of it through ``Cost.penalty`` (a :class:`Penalty`); their torch ``__call__`` stays
the reference, and ``tests/test_costs.py`` pins this pass to it (values and gradients, both presets, fp32 and fp64).
The kernel ``phase`` of :mod:`mpd.kernels` (its torch mode: each cost's own ``__call__``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numba import njit

from mpd import kernels
from mpd.costs.smoothness import NORM_EPS


@dataclass(frozen=True)
class Penalty:
    """A per-point penalty on the dense fields (0: q, 1: q', 2: q''), integrated with the phase weights w_i.

    ``norm_field``: c = |x|^2 / 2 (``squared``) or sqrt(|x|^2 + eta) / 2 on that field; ``limits``: per field None
    or (lo, hi) (dof,) each, c = |x - clamp(x, lo, hi)|^2 / 2 summed over the fields that have them."""

    norm_field: int | None = None
    squared: bool = False
    limits: tuple[tuple[torch.Tensor, torch.Tensor] | None, ...] | None = None


@njit(cache=True, nogil=True, fastmath={"reassoc"})
def _wsum(a, w):
    """sum_i a_i w_i, summed in whatever order the compiler vectorizes (the only reordered sums of the pass)."""
    acc = a.dtype.type(0)
    for i in range(a.shape[0]):
        acc += a[i] * w[i]
    return acc


@njit(cache=True, nogil=True, error_model="numpy")
def _phase_pass(X, w, norm_w, norm_sq, lim_w, lim_on, lo, hi, eps, values, G, sq, coef):
    """X, G (dof, B, 3, n) (the memory order of :meth:`mpd.trajectory.LinearTrajectory.dense`); w (n,); per field
    k: ``norm_w[k]`` (0: none), ``norm_sq[k]``, ``lim_w[k]``, ``lim_on[k]``, ``lo[k]``, ``hi[k]`` (dof,). Adds to
    values (4, B) (zeroed by the caller): the norm penalty of each field, then the limits'. ``sq``, ``coef`` (n,)
    scratch. Every inner loop runs along the n contiguous points of one joint and trajectory, with no branch in it
    (the compiler vectorizes them)."""
    dof, B, _, n = X.shape
    half = X.dtype.type(0.5)
    zero = X.dtype.type(0)
    for b in range(B):
        for k in range(3):
            nw = norm_w[k]
            if nw != 0:
                for i in range(n):
                    sq[i] = zero
                for j in range(dof):
                    x = X[j, b, k]
                    for i in range(n):
                        sq[i] += x[i] * x[i]
                if norm_sq[k]:
                    for i in range(n):
                        coef[i] = nw * w[i]
                else:
                    for i in range(n):
                        sq[i] = np.sqrt(sq[i] + eps)
                        coef[i] = half * nw * w[i] / sq[i]
                values[k, b] += half * _wsum(sq, w)
                for j in range(dof):
                    x = X[j, b, k]
                    g = G[j, b, k]
                    for i in range(n):
                        g[i] = coef[i] * x[i]
            else:
                for j in range(dof):
                    g = G[j, b, k]
                    for i in range(n):
                        g[i] = zero
            if lim_on[k]:
                for i in range(n):
                    sq[i] = zero
                    coef[i] = lim_w[k] * w[i]
                for j in range(dof):
                    x = X[j, b, k]
                    g = G[j, b, k]
                    lj, hj = lo[k, j], hi[k, j]
                    for i in range(n):
                        v = x[i] - min(max(x[i], lj), hj)
                        sq[i] += v * v
                        g[i] += coef[i] * v
                values[3, b] += half * _wsum(sq, w)


def phase_pass(
    stacked: torch.Tensor, w: torch.Tensor, penalties: list[tuple[Penalty, float]]
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """The unweighted value (B,) of each (penalty, weight) and the sum of their weighted gradients w.r.t. the
    stacked fields (B, 3, n, dof). At most one norm penalty per field and one set of limits."""
    B, _, n, dof = stacked.shape
    dt = stacked.dtype
    npdt = np.float32 if dt == torch.float32 else np.float64
    norm_w, norm_sq = np.zeros(3, npdt), np.zeros(3, np.bool_)
    lim_w, lim_on = np.zeros(3, npdt), np.zeros(3, np.bool_)
    lo, hi = np.zeros((3, dof), npdt), np.zeros((3, dof), npdt)
    slots = []
    for p, weight in penalties:
        if p.norm_field is not None:
            k = p.norm_field
            if norm_w[k] != 0:
                raise ValueError(f"two norm penalties on dense field {k}")
            norm_w[k], norm_sq[k] = weight, p.squared
            slots.append(k)
        else:
            if lim_on.any():
                raise ValueError("two sets of limits")
            for k, lim in enumerate(p.limits):
                if lim is not None:
                    lim_on[k], lim_w[k] = True, weight
                    lo[k], hi[k] = lim[0].numpy(), lim[1].numpy()
            slots.append(3)
    values = torch.zeros(4, B, dtype=dt)
    G = torch.empty_like(stacked)  # in the fields' memory layout
    X, Gp = stacked.permute(3, 0, 1, 2), G.permute(3, 0, 1, 2)  # (dof, B, 3, n) views
    scratch = np.empty((2, n), npdt)
    args = (norm_w, norm_sq, lim_w, lim_on, lo, hi, npdt(NORM_EPS), values.numpy(), Gp.numpy(), *scratch)
    _phase_pass(X.numpy(), w.numpy(), *args)
    return [values[k] for k in slots], G


def _parity(dtype: torch.dtype):
    """``run()``: the cost function's total and gradient w.r.t. the free rows (velocity, acceleration and joint
    limits among its terms) on 24 Panda trajectories through random configurations."""
    from mpd.costs.base import parity_case
    from mpd.costs.composite import CostFunction

    task, param, env, free, q_start, q_goal, ee_goal = parity_case("EnvSpheres3D-RobotPanda", dtype, 24, 34)
    cf = CostFunction(task, param, env, preset="official", sdf_mode="nearest")

    def run() -> dict:
        res = cf(free, q_start, q_goal, ee_goal)
        return {"total": res.total, "grad": res.grad, **{k: v for k, v in res.values.items()}}

    tol = {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    return run, tol


kernels.register(
    kernels.Kernel("phase", __name__, "the costs' __call__ (mpd.costs.velocity, acceleration, joint_limits)", _parity)
)
