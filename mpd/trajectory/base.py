"""Trajectories that are linear in their parameters.

Both parametrizations of the paper map a matrix of parameters W (control points or waypoints, ``(n_params, dof)``)
linearly to the dense phase trajectory on ``n_points`` equidistant phases s:

    Q = B W,   Q' = B' W,   Q'' = B'' W          (B, B', B'' of shape (n_points, n_params))

Some rows of W are fixed by the context (start configuration, goal configuration) and the others are free (what the
generative models produce). With W = A_free F + a_start q_start^T + a_goal q_goal^T, the dense trajectory and the
gradient of any cost of it w.r.t. the free rows are matrix products with precomputed matrices, on any batch size:

    dC/dF = (B A_free)^T dC/dQ + (B' A_free)^T dC/dQ' + (B'' A_free)^T dC/dQ''

Time derivatives use the linear phase-time map t = s T: q̇ = q' / T, q̈ = q'' / T².
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Dense:
    """A batch of dense trajectories: positions and phase derivatives, each (B, n_points, dof)."""

    q: torch.Tensor
    dq_ds: torch.Tensor
    ddq_ds2: torch.Tensor
    duration: float
    # the (B, 3, n_points, dof) buffer the three fields are views of, when they come from one (the fused phase
    # costs read it in one pass)
    stacked: torch.Tensor | None = None

    @property
    def dq_dt(self) -> torch.Tensor:
        return self.dq_ds / self.duration

    @property
    def ddq_dt2(self) -> torch.Tensor:
        return self.ddq_ds2 / self.duration**2


class LinearTrajectory:
    """Base class; subclasses set the basis matrices and the fixed-row structure in ``__init__``.

    Args:
        n_params: number of rows of W (control points or waypoints).
        n_points: dense phase points (128 in the paper).
        duration: trajectory duration T in seconds.
        ee_goal: True when the goal is an end-effector pose, so the final configuration is free.
    """

    name = "linear"

    def __init__(self, n_params: int, n_points: int, duration: float, ee_goal: bool):
        self.n_params = int(n_params)
        self.n_points = int(n_points)
        self.duration = float(duration)
        self.ee_goal = bool(ee_goal)
        self.phase = np.linspace(0.0, 1.0, self.n_points)
        self._cache: dict[tuple, dict[str, torch.Tensor]] = {}

    # subclasses fill these -----------------------------------------------------------------------------------
    basis: np.ndarray  # (n_points, n_params)
    basis_d1: np.ndarray
    basis_d2: np.ndarray
    a_free: np.ndarray  # (n_params, n_free) 0/1
    a_start: np.ndarray  # (n_params,)
    a_goal: np.ndarray  # (n_params,), zero with an end-effector goal

    @property
    def n_free(self) -> int:
        return self.a_free.shape[1]

    def settings(self) -> dict:
        """What identifies this parametrization (goes into dataset and model hashes)."""
        return {
            "name": self.name,
            "n_params": self.n_params,
            "n_points": self.n_points,
            "ee_goal": self.ee_goal,
        }

    def _t(self, dtype: torch.dtype, device) -> dict[str, torch.Tensor]:
        key = (dtype, str(device))
        if key not in self._cache:
            t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)  # noqa: E731
            mats = {}
            for k, b in (("0", self.basis), ("1", self.basis_d1), ("2", self.basis_d2)):
                mats["free" + k] = t(b @ self.a_free)
                mats["start" + k] = t(b @ self.a_start)
                mats["goal" + k] = t(b @ self.a_goal)
            # stacked (3 n_points, n_free): all three derivatives in one product (its transpose maps gradients back)
            mats["free_all"] = torch.cat([mats["free0"], mats["free1"], mats["free2"]], 0)
            # ... and with the start (and goal) configuration as extra rows of the operand: the whole dense
            # trajectory in one product, (3 n_points, n_free + 1 (+ 1))
            ends = [torch.cat([mats["start0"], mats["start1"], mats["start2"]])[:, None]]
            if not self.ee_goal:
                ends.append(torch.cat([mats["goal0"], mats["goal1"], mats["goal2"]])[:, None])
            mats["dense_all_t"] = torch.cat([mats["free_all"], *ends], 1).t().contiguous()
            mats["a_free"] = t(self.a_free)
            mats["a_start"] = t(self.a_start)
            mats["a_goal"] = t(self.a_goal)
            self._cache[key] = mats
        return self._cache[key]

    # -----------------------------------------------------------------------------------------------------------
    def full(self, free: torch.Tensor, q_start: torch.Tensor, q_goal: torch.Tensor | None = None) -> torch.Tensor:
        """All parameter rows W (B, n_params, dof) from the free rows (B, n_free, dof) and the context."""
        m = self._t(free.dtype, free.device)
        w = torch.einsum("ph,bhd->bpd", m["a_free"], free) + m["a_start"][None, :, None] * q_start[:, None, :]
        if not self.ee_goal:
            w = w + m["a_goal"][None, :, None] * q_goal[:, None, :]
        return w

    def free_rows(self, w: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`full`: the free rows of W (..., n_params, dof)."""
        idx = torch.as_tensor(self.a_free.argmax(0), device=w.device)
        return w[..., idx, :]

    def dense(self, free: torch.Tensor, q_start: torch.Tensor, q_goal: torch.Tensor | None = None) -> Dense:
        """Dense trajectory (q, q', q'') on the phase grid, each (B, n_points, dof)."""
        self._check(free, q_start, q_goal)
        m = self._t(free.dtype, free.device)
        B, n = free.shape[0], self.n_points
        # one product for the three derivatives and the start and goal terms, over the whole batch: rows (joint,
        # trajectory) of the operand times the stacked basis, (dof B, n_free + 2) x (n_free + 2, 3 n). The fields
        # are views of that (dof, B, 3, n) buffer: per joint and trajectory the points are contiguous, the layout
        # the fused phase costs (:mod:`mpd.costs.phase_kernel`) and the chain rule read.
        ends = [q_start[:, None]] if self.ee_goal else [q_start[:, None], q_goal[:, None]]
        a = torch.cat([free, *ends], 1)  # (B, n_free + 2, dof)
        dof = a.shape[2]
        out = torch.mm(a.permute(2, 0, 1).reshape(dof * B, -1), m["dense_all_t"]).view(dof, B, 3, n)
        stacked = out.permute(1, 2, 3, 0)  # (B, 3, n, dof)
        return Dense(stacked[:, 0], stacked[:, 1], stacked[:, 2], self.duration, stacked)

    def grad_to_free(
        self, g_q: torch.Tensor | None, g_dq: torch.Tensor | None = None, g_ddq: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Chain rule through the linear map: dC/d(free rows) (B, n_free, dof) from dC/dQ, dC/dQ', dC/dQ''."""
        ref = next(g for g in (g_q, g_dq, g_ddq) if g is not None)
        m = self._t(ref.dtype, ref.device)
        zero = torch.zeros_like(ref)
        g = torch.cat(
            [
                g_q if g_q is not None else zero,
                g_dq if g_dq is not None else zero,
                g_ddq if g_ddq is not None else zero,
            ],
            1,
        )  # (B, 3 n_points, dof)
        return torch.einsum("ph,bpd->bhd", m["free_all"], g)  # one matrix product (see dense)

    def grad_to_free_stacked(self, G: torch.Tensor) -> torch.Tensor:
        """:meth:`grad_to_free` of the three gradients stacked as (B, 3, n_points, dof) (no concatenation); one
        product in :meth:`dense`'s (dof, B, 3, n) memory layout when G has it (as ``torch.empty_like`` of the
        stacked fields does)."""
        m = self._t(G.dtype, G.device)
        B, _, n, dof = G.shape
        Gj = G.permute(3, 0, 1, 2)  # (dof, B, 3, n)
        if not Gj.is_contiguous():
            return torch.einsum("ph,bpd->bhd", m["free_all"], G.reshape(B, 3 * n, dof))
        return torch.mm(Gj.view(dof * B, 3 * n), m["free_all"]).view(dof, B, -1).permute(1, 2, 0).contiguous()

    def _check(self, free, q_start, q_goal):
        if free.ndim != 3 or free.shape[1] != self.n_free:
            raise ValueError(f"expected free parameters of shape (B, {self.n_free}, dof), got {tuple(free.shape)}")
        if q_start.shape != (free.shape[0], free.shape[2]):
            raise ValueError(f"q_start has shape {tuple(q_start.shape)}, expected {(free.shape[0], free.shape[2])}")
        if not self.ee_goal and (q_goal is None or q_goal.shape != q_start.shape):
            raise ValueError("a joint-goal trajectory needs q_goal of the same shape as q_start")

    def fit(self, paths: np.ndarray) -> np.ndarray:
        """Parameters W (N, n_params, dof) that follow dense paths (N, n, dof) from start to end."""
        raise NotImplementedError

    def param_phases(self) -> np.ndarray:
        """The phase each parameter row is attached to (n_params,): rows placed on a straight line at these
        phases give the straight-line trajectory (a linear function of s)."""
        raise NotImplementedError
