"""Compiled fast path of the end-effector pose cost on the CPU: pose, error, gradient and Jacobian product in one pass.

The torch path of :class:`mpd.costs.ee_pose.EEPoseCost` (the final configurations' kinematics gathered from the FK of
all configurations, :func:`mpd.costs.ee_pose.ee_pose_error` with the SE(3) logarithm and its exact gradient
(:mod:`mpd.costs.se3`), :meth:`mpd.robots.robot.Robot.ee_vjp`) is about a hundred torch operations on (B, 3) rows,
whose time is nearly all per-operation overhead. This pass (numba,
``cache=True``) does the same arithmetic row by row: the end-effector pose from the frame of its joint (read where
the FK left it), the error of either preset with the same branches (the series below the same angle, the axis
from the symmetric part near pi), the gradient and its product with the geometric Jacobian. It computes in float64
whatever the input's precision and rounds the results once; ``tests/test_costs.py`` pins it to the torch path.
The kernel ``ee_pose`` of :mod:`mpd.kernels`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit

from mpd import kernels
from mpd.costs.se3 import series_below


@njit(cache=True, nogil=True)
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True, nogil=True)
def _mm(A, B):
    """A B of 3 x 3 matrices (written out: numba's @ calls BLAS)."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return out


@njit(cache=True, nogil=True)
def _mv(A, x):
    """A x for a 3 x 3 matrix A."""
    out = np.empty(3)
    for i in range(3):
        out[i] = A[i, 0] * x[0] + A[i, 1] * x[1] + A[i, 2] * x[2]
    return out


@njit(cache=True, nogil=True)
def _so3_log(R, small):
    """Rotation vector (3,) and angle of R (3, 3), as :func:`mpd.costs.se3.so3_log` computes them."""
    w = np.empty(3)
    w[0] = (R[2, 1] - R[1, 2]) / 2
    w[1] = (R[0, 2] - R[2, 0]) / 2
    w[2] = (R[1, 0] - R[0, 1]) / 2
    cos = ((R[0, 0] + R[1, 1] + R[2, 2]) - 1) / 2
    sin = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    theta = math.atan2(sin, cos)
    t2 = theta * theta
    if theta < small:
        scale = 1 + t2 / 6 + 7 * t2 * t2 / 360 + 31 * t2 * t2 * t2 / 15120
    else:
        scale = theta / max(sin, 1e-30)
    phi = scale * w
    if cos < -0.9:  # the axis from the symmetric part (R + R^T)/2 - cos I = (1 - cos) n n^T
        k = 0
        for m in (1, 2):  # the first largest diagonal entry, as argmax
            if R[m, m] - cos > R[k, k] - cos:
                k = m
        col = np.empty(3)
        for m in range(3):
            col[m] = (R[m, k] + R[k, m]) / 2 - (cos if m == k else 0.0)
        norm = math.sqrt(max(col[k] * (1 - cos), 1e-30))
        sign = -1.0 if (col[0] * w[0] + col[1] * w[1] + col[2] * w[2]) / norm < 0 else 1.0
        for m in range(3):
            phi[m] = theta * sign * col[m] / norm
    return phi, theta


@njit(cache=True, nogil=True)
def _vinv_coeffs(theta, small):
    """c(theta) and c'(theta)/theta of :func:`mpd.costs.se3._vinv_coeffs`."""
    t2 = theta * theta
    if theta < small:
        c = 1 / 12 + t2 / 720 + t2 * t2 / 30240 + t2 * t2 * t2 / 1209600
        dc = 1 / 360 + t2 / 7560 + t2 * t2 / 201600
        return c, dc
    half_sin, half_cos = math.sin(theta / 2), math.cos(theta / 2)
    cot = half_cos / half_sin
    c = 1 / t2 - cot / (2 * theta)
    dc = -2 / (t2 * t2) + cot / (2 * t2 * theta) + 1 / (4 * t2 * half_sin * half_sin)
    return c, dc


@njit(cache=True, nogil=True)
def _official(pos, rot, gp, gR, small):
    """Value and (dC/dp, dC/dw) of 1/2 |log(T_goal T_ee^-1)|^2 (see :func:`mpd.costs.ee_pose.ee_pose_error`)."""
    R = _mm(gR, rot.T)
    t = gp - _mv(R, pos)
    phi, theta = _so3_log(R, small)
    c, dc = _vinv_coeffs(theta, small)
    pt = np.array(_cross(phi[0], phi[1], phi[2], t[0], t[1], t[2]))
    ppt = np.array(_cross(phi[0], phi[1], phi[2], pt[0], pt[1], pt[2]))
    rho = t - pt / 2 + c * ppt
    value = 0.5 * (np.sum(rho * rho) + np.sum(phi * phi))
    # the gradient of 1/2 |log(E exp(eps))|^2, as mpd.costs.se3.se3_half_sq_log_grad
    rt = np.array(_cross(rho[0], rho[1], rho[2], t[0], t[1], t[2]))
    dt_rho = rt / 2 + c * (np.sum(phi * t) * rho + t * np.sum(phi * rho) - 2 * phi * np.sum(t * rho))
    dt_rho += dc * phi * np.sum(ppt * rho)
    py = np.array(_cross(phi[0], phi[1], phi[2], dt_rho[0], dt_rho[1], dt_rho[2]))
    ppy = np.array(_cross(phi[0], phi[1], phi[2], py[0], py[1], py[2]))
    g_w = phi + dt_rho - py / 2 + c * ppy
    pr = np.array(_cross(phi[0], phi[1], phi[2], rho[0], rho[1], rho[2]))
    ppr = np.array(_cross(phi[0], phi[1], phi[2], pr[0], pr[1], pr[2]))
    g_v = _mv(R.T, rho + pr / 2 + c * ppr)
    # y = -[g_v; g_w]: dC/d(spatial twist of T_ee); dC/dp = y_v, dC/dw = y_w - p x y_v
    pxy = np.array(_cross(pos[0], pos[1], pos[2], -g_v[0], -g_v[1], -g_v[2]))
    return value, -g_v, -g_w - pxy


@njit(cache=True, nogil=True)
def _paper(pos, rot, gp, gR, small):
    """Value and (dC/dp, dC/dw) of 1/2 |p - p_goal|^2 + 1/2 |Log(R_goal^T R)|^2."""
    dp = pos - gp
    phi, _ = _so3_log(_mm(gR.T, rot), small)
    return 0.5 * np.sum(dp * dp) + 0.5 * np.sum(phi * phi), dp, _mv(rot, phi)


@njit(cache=True, nogil=True)
def _ee_pass(F, O, Z, cols, f, R_fix, p_fix, revolute, goal_pos, goal_rot, official, small, weight, value, g_last):
    """For each trajectory b: the end-effector pose of configuration ``cols[b]`` from the frames F (dof + 1, 4, 3, N)
    (frame ``f``: [R_f | p_f] transposed; the end effector at R_f R_fix, p_f + R_f p_fix), the cost of either preset
    into ``value[b]`` and ``weight`` J^T (dC/dp, dC/dw) into ``g_last[b]`` (dof,): for a joint k that moves the end
    effector, z_k . (dC/dw) + (z_k x (p - o_k)) . (dC/dp) when revolute, z_k . (dC/dp) when prismatic (origins O and
    axes Z (dof, 3, N))."""
    Rf = np.empty((3, 3))
    pf = np.empty(3)
    for b in range(cols.shape[0]):
        c = cols[b]
        for i in range(3):
            for m in range(3):
                Rf[i, m] = F[f, m, i, c]
            pf[i] = F[f, 3, i, c]
        rot = _mm(Rf, R_fix)
        pos = pf + _mv(Rf, p_fix)
        gp = goal_pos[b].astype(np.float64)
        gR = goal_rot[b].astype(np.float64)
        if official:
            v, g_p, g_w = _official(pos, rot, gp, gR, small)
        else:
            v, g_p, g_w = _paper(pos, rot, gp, gR, small)
        value[b] = v
        for k in range(f):
            z0, z1, z2 = np.float64(Z[k, 0, c]), np.float64(Z[k, 1, c]), np.float64(Z[k, 2, c])
            if revolute[k]:
                l0, l1, l2 = _cross(z0, z1, z2, pos[0] - O[k, 0, c], pos[1] - O[k, 1, c], pos[2] - O[k, 2, c])
                s = z0 * g_w[0] + z1 * g_w[1] + z2 * g_w[2] + l0 * g_p[0] + l1 * g_p[1] + l2 * g_p[2]
            else:
                s = z0 * g_p[0] + z1 * g_p[1] + z2 * g_p[2]
            g_last[b, k] = weight * s


def ee_pass(
    chain, kin, cols: torch.Tensor, goal_pos: torch.Tensor, goal_rot: torch.Tensor, preset: str, weight: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(cost (B,), ``weight`` dC/dq (B, dof)) of the configurations ``cols`` (B,) of ``kin`` (its frames, origins and
    axes: a kinematics with ``frames_t``) against the goals (B, 3), (B, 3, 3); ``preset``: ``official`` or
    ``paper``. Goals of another dtype are read as they are."""
    F = kin.frames_t
    dt = F.dtype
    B = cols.shape[0]
    value = np.empty(B, np.float64)
    g_last = np.zeros((B, chain.dof), np.float64)
    fix = chain.ee_fixed  # (4, 4) float64: the end effector in its joint's frame
    _ee_pass(
        F.numpy(),
        kin.origins_t.numpy(),
        kin.axes_t.numpy(),
        cols.numpy(),
        chain.ee_joint + 1,
        np.ascontiguousarray(fix[:3, :3]),
        np.ascontiguousarray(fix[:3, 3]),
        chain.revolute,
        goal_pos.detach().contiguous().numpy(),
        goal_rot.detach().contiguous().numpy(),
        preset == "official",
        series_below(dt),
        float(weight),
        value,
        g_last,
    )
    return torch.from_numpy(value).to(dt), torch.from_numpy(g_last).to(dt)


def _parity(dtype: torch.dtype):
    from mpd.costs.base import cost_parity

    tol = {"rtol": 2e-4, "atol": 2e-4} if dtype == torch.float32 else {"rtol": 1e-9, "atol": 1e-10}
    return cost_parity("ee_pose", dtype, 33), tol


kernels.register(
    kernels.Kernel(
        "ee_pose", __name__, "mpd.costs.ee_pose.ee_pose_error and mpd.robots.robot.Robot.ee_vjp (torch)", _parity
    )
)
