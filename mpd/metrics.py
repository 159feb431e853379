"""Metrics of a batch of planned trajectories for one context (the paper's section V-D, plus robometrics' fields).

All are computed on the dense trajectories, by the ground-truth checker (analytic SDF, margin 0), never by the
planner's own cost: success (at least one valid trajectory), fraction valid (collision free and within position,
velocity and acceleration limits), Vendi diversity of the valid ones (kernel exp(-||a - b||^2) on the dense
joint trajectories, as in the paper; missing (NaN) with fewer than two valid trajectories, as the authors record
it), end-effector position (m) and orientation (deg) errors, smoothness (sum over time of the acceleration norm),
path length (joint space); mean over the valid trajectories, and for the best trajectory chosen by a rule.

End-effector errors are the authors' (the ones behind the paper's 2.0 / 5.2 / 7.4 cm): with the twist
xi = [rho; phi] = log(T_goal T_ee^-1) (SE(3) log), ``ee_pos_error`` = ||rho|| and ``ee_ori_error_deg`` = ||phi||
in degrees (the geodesic angle). rho is not the Euclidean offset: it carries an orientation x reach term, so
``ee_pos_error_euclidean`` = ||p_ee - p_goal|| is reported beside it. The best trajectory of an end-effector-goal
task is the valid one of lowest ``ee_pos_error`` (the authors' rule).
"""

from __future__ import annotations

import math

import torch

from mpd.collision import CollisionChecker, Validity
from mpd.costs.se3 import se3_log
from mpd.trajectory import Dense

METRICS = (
    "success",
    "fraction_valid",
    "n_valid",
    "vendi",
    "ee_pos_error",
    "ee_pos_error_euclidean",
    "ee_ori_error_deg",
    "smoothness",
    "path_length",
    "best_path_length",
    "best_ee_pos_error",
    "best_ee_pos_error_euclidean",
    "best_ee_ori_error_deg",
    "best_smoothness",
    "collision_fraction",
    "self_collision_fraction",
    "limit_violation_fraction",
)
BEST_RULES = ("shortest", "ee_error")


def vendi_score(x: torch.Tensor) -> float:
    """Vendi score of samples x (n, ...) with kernel exp(-||a - b||^2): exp of the Shannon entropy of the eigenvalues
    of K / n. 1 for identical samples, n for samples far apart; NaN without samples."""
    n = x.shape[0]
    if n == 0:
        return float("nan")
    f = x.reshape(n, -1).double()
    sq = (f * f).sum(1)
    d2 = (sq[:, None] + sq[None, :] - 2 * f @ f.T).clamp_min(0)
    lam = torch.linalg.eigvalsh(torch.exp(-d2) / n).clamp_min(0)
    lam = lam[lam > 0]
    return float(torch.exp(-(lam * torch.log(lam)).sum()))


def path_length(q: torch.Tensor) -> torch.Tensor:
    """Joint-space length of dense paths (B, n, dof) -> (B,)."""
    return (q[:, 1:] - q[:, :-1]).norm(dim=-1).sum(-1)


def smoothness(ddq_dt2: torch.Tensor) -> torch.Tensor:
    """Sum over the dense points of the acceleration norm (the paper's footnote: "sum of accelerations") -> (B,)."""
    return ddq_dt2.norm(dim=-1).sum(-1)


def rotation_angle_deg(r1: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
    """Geodesic angle between rotations (..., 3, 3), degrees."""
    c = ((r1.transpose(-1, -2) @ r2).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.rad2deg(torch.arccos(c.clamp(-1.0, 1.0)))


def ee_pose_errors(
    p_ee: torch.Tensor, r_ee: torch.Tensor, p_goal: torch.Tensor, r_goal: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(log position error (m), orientation error (deg), Euclidean position error (m)) of end-effector poses
    (..., 3), (..., 3, 3) against goal poses (broadcast). The first two are the norms of the translation and rotation
    parts of the twist log(T_goal T_ee^-1), the authors' definition."""
    r_rel = r_goal @ r_ee.transpose(-1, -2)
    t_rel = p_goal - (r_rel @ p_ee[..., None])[..., 0]
    xi, _ = se3_log(r_rel, t_rel)
    return xi[..., :3].norm(dim=-1), torch.rad2deg(xi[..., 3:].norm(dim=-1)), (p_ee - p_goal).norm(dim=-1)


def _mean(x: torch.Tensor) -> float:
    return float(x.double().mean()) if x.numel() else float("nan")


def evaluate(
    checker: CollisionChecker,
    dense: Dense,
    *,
    q_goal: torch.Tensor | None = None,
    ee_goal: tuple[torch.Tensor, torch.Tensor] | None = None,
    best: str = "auto",
) -> tuple[dict[str, float], Validity, int | None]:
    """Metrics of one context's batch of dense trajectories (B, n, dof).

    Returns (metrics, per-trajectory validity, index of the best valid trajectory or None). ``best`` is
    ``shortest`` (shortest joint-space path), ``ee_error`` (smallest end-effector position error) or ``auto``
    (the authors' rule: ``ee_error`` with an end-effector goal, else ``shortest``).
    """
    q, dq, ddq = dense.q, dense.dq_dt, dense.ddq_dt2
    val = checker.trajectories(q, dq, ddq)
    valid = val.valid
    idx = torch.nonzero(valid).flatten()
    lengths = path_length(q)
    smooth = smoothness(ddq)
    robot = checker.robot
    if ee_goal is not None or q_goal is not None:
        # a joint goal: the end-effector error is that of the final configuration vs FK of the goal (0 for B-splines)
        p_end, r_end = robot.ee_pose(q[:, -1])
        if ee_goal is not None:
            p_goal, r_goal = ee_goal[0].to(q), ee_goal[1].to(q)
        else:
            p_goal, r_goal = robot.ee_pose(q_goal.to(q)[None])
        pos_err, ori_err, pos_err_euc = ee_pose_errors(p_end, r_end, p_goal, r_goal)
    else:
        pos_err = ori_err = pos_err_euc = torch.zeros_like(lengths)
    rule = best if best != "auto" else ("ee_error" if ee_goal is not None else "shortest")
    if rule not in BEST_RULES:
        raise ValueError(f"unknown best-trajectory rule {best!r} (auto, {', '.join(BEST_RULES)})")
    b = None
    if len(idx):
        key = lengths if rule == "shortest" else pos_err
        b = int(idx[key[idx].argmin()])
    nan = float("nan")
    out = {
        "success": float(len(idx) > 0),
        "fraction_valid": _mean(valid.float()),
        "n_valid": float(len(idx)),
        "vendi": vendi_score(q[idx]) if len(idx) > 1 else nan,
        "ee_pos_error": _mean(pos_err[idx]),
        "ee_pos_error_euclidean": _mean(pos_err_euc[idx]),
        "ee_ori_error_deg": _mean(ori_err[idx]),
        "smoothness": _mean(smooth[idx]),
        "path_length": _mean(lengths[idx]),
        "best_path_length": float(lengths[b]) if b is not None else nan,
        "best_ee_pos_error": float(pos_err[b]) if b is not None else nan,
        "best_ee_pos_error_euclidean": float(pos_err_euc[b]) if b is not None else nan,
        "best_ee_ori_error_deg": float(ori_err[b]) if b is not None else nan,
        "best_smoothness": float(smooth[b]) if b is not None else nan,
        "collision_fraction": _mean((~val.env_free).float()),
        "self_collision_fraction": _mean((~val.self_free).float()),
        "limit_violation_fraction": _mean((~val.limits_ok).float()),
    }
    assert set(out) == set(METRICS)
    for k, v in out.items():
        if isinstance(v, float) and math.isinf(v):
            out[k] = nan
    return out, val, b
