"""Batched inverse kinematics of the end-effector pose: damped least squares with random restarts.

All targets and all restarts are one batch of ``n_targets * n_restarts`` configurations that iterate together
(no autograd: the geometric Jacobian comes from :meth:`Robot.ee_jacobian`):

    e  = [p* - p ;  log(R* R^T)]                       (world frame, the Jacobian's convention)
    dq = J^T (J J^T + lambda^2 I)^-1 e                 (steps capped so that the linearisation holds)
    q  = clamp(q + dq, q_min, q_max)

A restart stops moving once it is within the tolerances. Planar robots work unchanged: their Jacobian rows for
z, roll and pitch are zero and so are the errors there. Results depend only on the inputs and the generator, on
every CPU: the FK, the products and the 6 x 6 solve are the fixed-order ones of :mod:`mpd.robots.exact` (MKL's
processor-specific kernels changed the last bits of the solutions, and with them the datasets' contexts).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from mpd.robots.exact import mm, spd_solve
from mpd.robots.robot import Robot


@dataclass
class IKResult:
    """Per target: the chosen configuration, whether it meets the tolerances (and ``valid``), its errors."""

    q: torch.Tensor  # (N, dof)
    success: torch.Tensor  # (N,) bool
    pos_err: torch.Tensor  # (N,) m
    rot_err: torch.Tensor  # (N,) rad
    n_success_restarts: torch.Tensor  # (N,) restarts that met the tolerances (and ``valid``)


def rotation_log(r: torch.Tensor) -> torch.Tensor:
    """Rotation vector (..., 3) of rotation matrices (..., 3, 3)."""
    v = 0.5 * torch.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    s = v.norm(dim=-1)  # sin(angle)
    c = 0.5 * (r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2] - 1.0)
    angle = torch.atan2(s, c)
    # angle / sin(angle) -> 1 at 0; near pi the axis from v is poorly defined, but the magnitude is right
    scale = torch.where(s > 1e-12, angle / s.clamp_min(1e-12), torch.ones_like(s))
    return v * scale[..., None]


def pose_errors(robot: Robot, q: torch.Tensor, pos: torch.Tensor, rot: torch.Tensor | None):
    """Position error (...) in m and orientation error (...) in rad of configurations q against targets."""
    p, r = robot.ee_pose(q, exact=True)
    ep = (pos - p).norm(dim=-1)
    if rot is None:
        return ep, torch.zeros_like(ep)
    return ep, rotation_log(mm(rot, r.transpose(-1, -2))).norm(dim=-1)


def solve_ik(
    robot: Robot,
    pos: torch.Tensor,
    rot: torch.Tensor | None = None,
    *,
    n_restarts: int = 16,
    generator: torch.Generator | None = None,
    q_init: torch.Tensor | None = None,
    max_iters: int = 300,
    damping: float = 0.05,
    max_step_pos: float = 0.1,
    max_step_rot: float = 0.5,
    pos_tol: float = 5e-3,
    rot_tol_deg: float = 1.0,
    valid: Callable[[torch.Tensor], torch.Tensor] | None = None,
    q_ref: torch.Tensor | None = None,
    q_restarts: torch.Tensor | None = None,
    valid_target: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
) -> IKResult:
    """Configurations whose end-effector pose reaches targets (pos (N, 3), rot (N, 3, 3) or None for position
    only).

    Args:
        n_restarts: random initial configurations per target (uniform within the limits, from ``generator``).
        q_init: optional initial configurations (N, dof) used as the first restart of each target.
        valid: optional extra test of converged configurations (M, dof) -> (M,) bool, e.g. collision free.
        q_ref: optional (N, dof); among the successful restarts the one closest to it is returned
            (default: the successful restart with the lowest index).
        q_restarts: optional (N, R, dof): the initial configurations of every restart, instead of drawing them
            from ``generator`` (a batch of targets whose restarts come from separate streams; a target's result
            does not depend on the other targets of the batch).
        valid_target: like ``valid`` but also given the target index (M,) of each configuration.
    """
    dtype = pos.dtype if pos.is_floating_point() else torch.float64
    pos = pos.to(dtype)
    rot = rot.to(dtype) if rot is not None else None
    N, R, dof = pos.shape[0], int(n_restarts), robot.dof
    lo, hi = robot.limits(pos)
    if q_restarts is not None:
        if q_restarts.shape != (N, R, dof):
            raise ValueError(f"q_restarts has shape {tuple(q_restarts.shape)}, expected {(N, R, dof)}")
        q = q_restarts.to(device=pos.device, dtype=dtype).clone()
    else:
        q = robot.random_q(N * R, generator, dtype=dtype).reshape(N, R, dof).to(pos.device)
    if valid_target is not None:
        if valid is not None:
            raise ValueError("give valid or valid_target, not both")
        valid = _with_targets(valid_target, R)
    if q_init is not None:
        q[:, 0] = torch.minimum(torch.maximum(q_init.to(q), lo), hi)
    q = q.reshape(N * R, dof)
    tp = pos.repeat_interleave(R, 0)
    tr = rot.repeat_interleave(R, 0) if rot is not None else None
    rot_tol = math.radians(rot_tol_deg)
    eye6 = torch.eye(6, dtype=dtype, device=q.device)
    ok = torch.zeros(N * R, dtype=torch.bool, device=q.device)  # converged (and valid)
    active = torch.ones(N * R, dtype=torch.bool, device=q.device)  # still iterating
    for _ in range(max_iters):
        idx = active.nonzero()[:, 0]
        if len(idx) == 0:
            break
        kin = robot.kinematics(q[idx], spheres=False, ee=True, exact=True)
        e_pos = tp[idx] - kin.ee_pos
        e_rot = rotation_log(mm(tr[idx], kin.ee_rot.transpose(-1, -2))) if tr is not None else torch.zeros_like(e_pos)
        # iterate to a tenth of the tolerances: near a solution DLS converges fast, and the margin keeps a
        # solution inside the tolerances after float32 round trips or a re-check with another FK
        conv = (e_pos.norm(dim=-1) < 0.1 * pos_tol) & (e_rot.norm(dim=-1) < 0.1 * rot_tol)
        if conv.any():
            new = idx[conv]
            active[new] = False
            ok[new] = _valid(valid, q[new], new)
            if q_ref is None:  # one success per target is enough: stop its other restarts
                solved = ok.view(N, R).any(1)
                active &= ~solved.repeat_interleave(R)
        run = ~conv & active[idx]
        if not run.any():
            continue
        rows = idx[run]
        # cap the task-space step: far from the target the linearisation is poor
        ep, er = e_pos[run], e_rot[run]
        ep = ep * (max_step_pos / ep.norm(dim=-1, keepdim=True).clamp_min(max_step_pos))
        er = er * (max_step_rot / er.norm(dim=-1, keepdim=True).clamp_min(max_step_rot))
        e = torch.cat([ep, er], -1)
        J = robot.chain.ee_jacobian(kin)[run]
        if tr is None:
            J[:, 3:] = 0  # position only
        A = mm(J, J.transpose(-1, -2)) + damping**2 * eye6
        dq = mm(J.transpose(-1, -2), spd_solve(A, e)[..., None])[..., 0]
        q[rows] = torch.minimum(torch.maximum(q[rows] + dq, lo), hi)
    ep, er = pose_errors(robot, q, tp, tr)
    within = (ep < pos_tol) & (er < rot_tol)
    late = within & active  # reached the tolerances but not a tenth of them
    if late.any():
        ok[late] = _valid(valid, q[late], late.nonzero()[:, 0])
    ok &= within
    return _choose(q.view(N, R, dof), ok.view(N, R), ep.view(N, R), er.view(N, R), q_ref)


class _with_targets:
    """``valid(q)`` for rows of the (N * R) batch from ``valid_target(q, target)``: the rows are passed along."""

    def __init__(self, fn, R: int):
        self.fn, self.R = fn, R

    def rows(self, q: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        return self.fn(q, torch.div(rows, self.R, rounding_mode="floor"))


def _valid(valid, q: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
    if valid is None or len(q) == 0:
        return torch.ones(len(q), dtype=torch.bool, device=q.device)
    out = valid.rows(q, rows) if isinstance(valid, _with_targets) else valid(q)
    return torch.as_tensor(out, dtype=torch.bool, device=q.device)


def _choose(q, ok, ep, er, q_ref) -> IKResult:
    N, R, _ = q.shape
    ar = torch.arange(R, device=q.device, dtype=q.dtype)
    if q_ref is not None:
        key = (q - q_ref.to(q)[:, None]).norm(dim=-1)
    else:
        key = ar.expand(N, R)
    # successful restarts by key; otherwise the smallest (normalised) pose error
    fail_key = ep / 5e-3 + er / math.radians(1.0)
    score = torch.where(ok, key, torch.full_like(key, float("inf")))
    best_ok = score.argmin(1)
    best_fail = fail_key.argmin(1)
    any_ok = ok.any(1)
    pick = torch.where(any_ok, best_ok, best_fail)
    rows = torch.arange(N, device=q.device)
    return IKResult(q[rows, pick], any_ok, ep[rows, pick], er[rows, pick], ok.sum(1))
