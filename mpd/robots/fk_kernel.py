"""Compiled fast path of the batch-last forward kinematics on the CPU (:meth:`mpd.robots.chain.KinematicChain.forward`).

The torch pass runs one (11, 3) x (3, 3B) product per joint and one (points, 4) x (4, 3B) product per frame with
points: matrix products of an inner dimension of 3 or 4, which BLAS runs at a fraction of the machine's speed, and
which on a 2-core CPU were at times several times slower again (MKL's sgemm, over stretches of minutes, in every
process; the elementwise kernels were not). This kernel (numba,
``cache=True``) does the same arithmetic, term by term in the order of those products, in loops along the
configurations (which the compiler vectorizes): the frames, joint axes, joint origins and attached points in one
pass, in blocks of configurations that stay in the first-level cache.

The kernel ``fk`` of :mod:`mpd.kernels`: ``tests/test_costs_chain.py`` pins it to the torch pass (the batch-first
formulation and the BLAS products), for every robot, in float32 and float64, and ``tests/test_kernels.py`` on the
Panda through the switch.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from mpd import kernels

BLOCK = 512  # configurations per block: the (11, block) scratch of one joint fits the 32 KB first-level cache


@njit(cache=True, nogil=True, error_model="numpy")
def _fk_pass(J, revolute, A, s, co, qt, W, frame, F, axes, origins, pts, P):
    """J (dof, 11, 3): the rows [Off_R; Off_R K; Off_R K^2; axis; off_p] of each joint against the parent rotation;
    A (dof, 3): the joint axes; s, co, qt (dof, N): sin q, 1 - cos q, q; W (P, 4), frame (P,): the points' [l; 1]
    weights and frames. Writes F (dof + 1, 4, 3, N) (frame 0 set by the caller), axes and origins (dof, 3, N), pts
    (P, 3, N). P (11, block): scratch. Every inner loop runs along one block of configurations, on rows taken
    as 1-D views (the form the compiler vectorizes)."""
    dof = J.shape[0]
    N = F.shape[3]
    n_pts = W.shape[0]
    B = P.shape[1]
    for c0 in range(0, N, B):
        n = min(N, c0 + B) - c0
        for j in range(dof):
            for a in range(3):
                # P[r] = sum_b J[j, r, b] R[b, a] with R = F[j, :3]: column a of every row of the product
                r0 = F[j, 0, a, c0 : c0 + n]
                r1 = F[j, 1, a, c0 : c0 + n]
                r2 = F[j, 2, a, c0 : c0 + n]
                for r in range(11):
                    j0, j1, j2 = J[j, r, 0], J[j, r, 1], J[j, r, 2]
                    pr = P[r]
                    for k in range(n):
                        pr[k] = j0 * r0[k] + j1 * r1[k] + j2 * r2[k]
                p3 = F[j, 3, a, c0 : c0 + n]
                o = origins[j, a, c0 : c0 + n]
                p10 = P[10]
                for k in range(n):
                    o[k] = p3[k] + p10[k]
                if revolute[j]:
                    sj = s[j, c0 : c0 + n]
                    cj = co[j, c0 : c0 + n]
                    for b in range(3):
                        out = F[j + 1, b, a, c0 : c0 + n]
                        pb, pb3, pb6 = P[b], P[3 + b], P[6 + b]
                        for k in range(n):
                            out[k] = pb[k] + sj[k] * pb3[k] + cj[k] * pb6[k]
                    ax = axes[j, a, c0 : c0 + n]
                    pn = F[j + 1, 3, a, c0 : c0 + n]
                    p9 = P[9]
                    for k in range(n):
                        ax[k] = p9[k]
                        pn[k] = o[k]
                else:
                    for b in range(3):
                        out = F[j + 1, b, a, c0 : c0 + n]
                        pb = P[b]
                        for k in range(n):
                            out[k] = pb[k]
            if not revolute[j]:
                # the world axis R Off_R a, and the joint's travel along it
                a0, a1, a2 = A[j, 0], A[j, 1], A[j, 2]
                qj = qt[j, c0 : c0 + n]
                for a in range(3):
                    r0 = F[j + 1, 0, a, c0 : c0 + n]
                    r1 = F[j + 1, 1, a, c0 : c0 + n]
                    r2 = F[j + 1, 2, a, c0 : c0 + n]
                    ax = axes[j, a, c0 : c0 + n]
                    o = origins[j, a, c0 : c0 + n]
                    pn = F[j + 1, 3, a, c0 : c0 + n]
                    for k in range(n):
                        ax[k] = a0 * r0[k] + a1 * r1[k] + a2 * r2[k]
                        pn[k] = o[k] + ax[k] * qj[k]
        for p in range(n_pts):
            f = frame[p]
            w0, w1, w2, w3 = W[p, 0], W[p, 1], W[p, 2], W[p, 3]
            for a in range(3):
                r0 = F[f, 0, a, c0 : c0 + n]
                r1 = F[f, 1, a, c0 : c0 + n]
                r2 = F[f, 2, a, c0 : c0 + n]
                r3 = F[f, 3, a, c0 : c0 + n]
                out = pts[p, a, c0 : c0 + n]
                for k in range(n):
                    out[k] = w0 * r0[k] + w1 * r1[k] + w2 * r2[k] + w3 * r3[k]


def fk_pass(
    J: torch.Tensor,
    revolute: np.ndarray,
    A: torch.Tensor,
    qt: torch.Tensor,
    W: np.ndarray,
    frame: np.ndarray,
    points: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Frames (dof + 1, 4, 3, N), axes and origins (dof, 3, N) and, with ``points``, the points (P, 3, N) of the
    configurations qt (dof, N) (see :func:`_fk_pass`)."""
    dof, N = qt.shape
    dt = qt.dtype
    F = torch.empty(dof + 1, 4, 3, N, dtype=dt)
    F[0].zero_()
    for a in range(3):
        F[0, a, a] = 1.0
    axes = torch.empty(dof, 3, N, dtype=dt)
    origins = torch.empty(dof, 3, N, dtype=dt)
    n_pts = W.shape[0] if points else 0
    pts = torch.empty(n_pts, 3, N, dtype=dt)
    s, co = torch.sin(qt), 1 - torch.cos(qt)
    npdt = np.float32 if dt == torch.float32 else np.float64
    scratch = np.empty((11, min(BLOCK, max(N, 1))), npdt)
    _fk_pass(
        J.numpy(), revolute, A.numpy(), s.numpy(), co.numpy(), qt.numpy(), W[:n_pts].astype(npdt, copy=False),
        frame[:n_pts], F.numpy(), axes.numpy(), origins.numpy(), pts.numpy(), scratch,
    )  # fmt: skip
    return F, axes, origins, pts if points else None


def _parity(dtype: torch.dtype):
    """The Panda's FK of 600 random configurations (more than a block): frames, axes, origins, points, EE pose."""
    from mpd.robots.robot import get_robot

    chain = get_robot("RobotPanda").chain
    q = torch.randn(600, chain.dof, generator=torch.Generator().manual_seed(8), dtype=dtype) * 1.5

    def run() -> dict:
        k = chain.forward(q)
        return {f: getattr(k, f) for f in ("frames_t", "axes_t", "origins_t", "points_t", "ee_pos", "ee_rot")}

    return run, {"rtol": 0.0, "atol": 2e-6 if dtype == torch.float32 else 1e-14}


kernels.register(
    kernels.Kernel("fk", __name__, "mpd.robots.chain.KinematicChain._forward_general (the torch pass)", _parity)
)
