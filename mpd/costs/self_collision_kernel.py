"""Compiled fast path of the self-collision cost on the CPU: culling, the deepest pair and its Jacobian product.

:class:`mpd.costs.self_collision.SelfCollisionCost` culls in torch with bounding spheres of whole frames, then of
clusters, then takes the maximum over all sphere pairs of the configurations that remain, as passes over index gathers
(costly for the few configurations that need the exact pass). This kernel (numba, ``cache=True``) makes the same tests:
the same bounding spheres, the same pairs, the same penetration ``r_i + r_j + eps - d_ij`` and its deepest pair (the
first of equal ones in the torch path's order), each level a pair at a time over all the configurations still in, loops
the compiler vectorizes. Given the kinematics it also maps the deepest pairs' gradients to the joints
(:func:`_pair_vjp`), so the few active configurations need no torch pass. The kernel ``self_collision`` of
:mod:`mpd.kernels`.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from mpd import kernels
from mpd.costs.collision_kernel import column_ranges, run_columns


@njit(cache=True, nogil=True)
def _gather(X, rows, cand, M):
    """The centres of spheres ``rows`` in the configurations ``cand[:M]``, contiguous: (len(rows), 3, M)."""
    out = np.empty((rows.shape[0], 3, M), X.dtype)
    for r in range(rows.shape[0]):
        s = rows[r]
        for e in range(3):
            x = X[s, e]
            o = out[r, e]
            for m in range(M):
                o[m] = x[cand[m]]
    return out


@njit(cache=True, nogil=True)
def _cull(Y, a, b, r2, flag):
    """``flag[m]`` = 1 where some pair (a[k], b[k]) of rows of Y (R, 3, M) is closer than sqrt(r2[k])."""
    flag[:] = 0
    for k in range(a.shape[0]):
        ya0, ya1, ya2 = Y[a[k], 0], Y[a[k], 1], Y[a[k], 2]
        yb0, yb1, yb2 = Y[b[k], 0], Y[b[k], 1], Y[b[k], 2]
        r = r2[k]
        for m in range(flag.shape[0]):
            d0 = ya0[m] - yb0[m]
            d1 = ya1[m] - yb1[m]
            d2 = ya2[m] - yb2[m]
            flag[m] |= d0 * d0 + d1 * d1 + d2 * d2 < r


@njit(cache=True, nogil=True)
def _pair_vjp(X, c, i, j, coef, joint, revolute, O, Z, out):
    """Add J^T g of configuration c to ``out[c]`` (dof,), for g = coef (c_i - c_j) on centre j and -g on centre i:
    (J^T g)_k = z_k . ((x - o_k) x g) for a revolute joint k that moves the sphere, z_k . g for a prismatic one
    (``joint[s]``: the last joint that moves sphere s, -1 for none)."""
    g0 = coef * (X[i, 0, c] - X[j, 0, c])
    g1 = coef * (X[i, 1, c] - X[j, 1, c])
    g2 = coef * (X[i, 2, c] - X[j, 2, c])
    for s, sign in ((j, 1.0), (i, -1.0)):
        x0, x1, x2 = X[s, 0, c], X[s, 1, c], X[s, 2, c]
        for k in range(joint[s] + 1):
            z0, z1, z2 = Z[k, 0, c], Z[k, 1, c], Z[k, 2, c]
            if revolute[k]:
                p0, p1, p2 = x0 - O[k, 0, c], x1 - O[k, 1, c], x2 - O[k, 2, c]
                t = z0 * (p1 * g2 - p2 * g1) + z1 * (p2 * g0 - p0 * g2) + z2 * (p0 * g1 - p1 * g0)
            else:
                t = z0 * g0 + z1 * g1 + z2 * g2
            out[c, k] += sign * t


@njit(cache=True, nogil=True)
def _self_pass(
    X, c0, c1, a1, b1, r1, refs2, a2, b2, r2, used, pi, pj, rr, pen_out, cfg, best_i, best_j, grad, ww, n, joint,
    revolute, O, Z, g_out,
):  # fmt: skip
    """For every configuration c0 <= c < c1 of X (S, 3, N): if some frame pair (a1, b1, squared reach r1) and then some
    cluster pair (a2, b2 into the reference spheres ``refs2``, r2) may touch, the maximum over the pairs (pi, pj into
    the ``used`` spheres) of rr - d, written to ``pen_out[c]`` where positive (else it stays 0); the configurations
    with a positive one, and their deepest pair (the first of equal ones; sphere indices), go to ``cfg``, ``best_i``,
    ``best_j``; returns their number. With ``grad``, also adds the gradient of sum_c ww[c % n] pen[c] w.r.t. the
    joints to ``g_out`` (N, dof), through the deepest pairs (``joint``, ``revolute``, origins O and axes Z (dof, 3,
    N): see :func:`_pair_vjp`).

    Each level tests a pair at a time over all the configurations still in (contiguous rows: the first level reads
    X's rows as they are, the others gather the centres they need once); a Panda batch of random-weight samples,
    12800 configurations: 3707 after the frames, 751 after the clusters.
    """
    n1 = c1 - c0
    flag = np.empty(n1, np.uint8)
    # level 1 on X's own rows, shifted to the range
    flag[:] = 0
    for k in range(a1.shape[0]):
        xa0, xa1, xa2 = X[a1[k], 0, c0:c1], X[a1[k], 1, c0:c1], X[a1[k], 2, c0:c1]
        xb0, xb1, xb2 = X[b1[k], 0, c0:c1], X[b1[k], 1, c0:c1], X[b1[k], 2, c0:c1]
        r = r1[k]
        for m in range(n1):
            d0 = xa0[m] - xb0[m]
            d1 = xa1[m] - xb1[m]
            d2 = xa2[m] - xb2[m]
            flag[m] |= d0 * d0 + d1 * d1 + d2 * d2 < r
    cand = np.empty(n1, np.int64)
    M = 0
    for m in range(n1):
        cand[M] = c0 + m
        M += flag[m]
    if M == 0:
        return 0
    # level 2 on the clusters' reference spheres
    Y = _gather(X, refs2, cand, M)
    flag2 = np.empty(M, np.uint8)
    _cull(Y, a2, b2, r2, flag2)
    M2 = 0
    for m in range(M):
        cand[M2] = cand[m]
        M2 += flag2[m]
    if M2 == 0:
        return 0
    # the exact pass over all pairs of the used spheres
    Xc = _gather(X, used, cand, M2)
    best = np.full(M2, -np.inf, X.dtype)
    bk = np.full(M2, -1, np.int64)
    for k in range(pi.shape[0]):
        xi0, xi1, xi2 = Xc[pi[k], 0], Xc[pi[k], 1], Xc[pi[k], 2]
        xj0, xj1, xj2 = Xc[pj[k], 0], Xc[pj[k], 1], Xc[pj[k], 2]
        r = rr[k]
        for m in range(M2):
            d0 = xi0[m] - xj0[m]
            d1 = xi1[m] - xj1[m]
            d2 = xi2[m] - xj2[m]
            p = r - np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            better = p > best[m]
            best[m] = p if better else best[m]
            bk[m] = k if better else bk[m]
    na = 0
    for m in range(M2):
        if best[m] > 0:
            c = cand[m]
            i = used[pi[bk[m]]]
            j = used[pj[bk[m]]]
            pen_out[c] = best[m]
            cfg[na] = c
            best_i[na] = i
            best_j[na] = j
            na += 1
            if grad:
                u0 = X[i, 0, c] - X[j, 0, c]
                u1 = X[i, 1, c] - X[j, 1, c]
                u2 = X[i, 2, c] - X[j, 2, c]
                coef = ww[c % n] / max(np.sqrt(u0 * u0 + u1 * u1 + u2 * u2), 1e-12)
                _pair_vjp(X, c, i, j, coef, joint, revolute, O, Z, g_out)
    return na


def kernel_args(levels, blocks, used: np.ndarray, radii: np.ndarray, margin: float, dtype) -> tuple:
    """Flat pair arrays from the cost's bounding-sphere levels and exact blocks, in the torch path's order (block by
    block, row-major within a block): the frames' pairs as sphere indices, the clusters' as indices into their
    reference spheres, the exact pairs as indices into the ``used`` spheres."""
    np_dtype = torch.empty(0, dtype=dtype).numpy().dtype
    pairs = []
    for level in levels:
        a = np.concatenate([np.repeat(A, len(B)) for A, B, _ in level]).astype(np.int64)
        b = np.concatenate([np.tile(B, len(A)) for A, B, _ in level]).astype(np.int64)
        r = np.concatenate([R.reshape(-1) for _, _, R in level]).astype(np_dtype)
        pairs.append((a, b, r))
    (a1, b1, r1), (a2, b2, r2) = pairs
    refs2 = np.unique(np.concatenate([a2, b2]))
    pi = np.concatenate([np.repeat(I, len(J)) for I, J in blocks]).astype(np.int64)
    pj = np.concatenate([np.tile(J, len(I)) for I, J in blocks]).astype(np.int64)
    rr = np.concatenate([(radii[used[I]][:, None] + radii[used[J]][None, :] + margin).reshape(-1) for I, J in blocks])
    local = lambda x: np.searchsorted(refs2, x).astype(np.int64)  # noqa: E731
    return (a1, b1, r1, refs2, local(a2), local(b2), r2, used.astype(np.int64), pi, pj, rr.astype(np_dtype))


def self_pass(
    X: torch.Tensor, args: tuple, grad: tuple | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """(per-configuration penetration (N,), active configurations (M,), their deepest pair i (M,), j (M,), dC/dq (N,
    dof) or None); the configurations split over threads as in :func:`mpd.costs.collision_kernel.column_ranges`.

    ``grad``: (kinematics of the N configurations, per-point weights ww (n,) of the N = B n configurations, the
    chain): the gradient of sum_c ww[c % n] pen[c] w.r.t. each configuration's joints, through its deepest pair."""
    N = X.shape[2]
    Xn = X.detach().contiguous().numpy()
    pen = torch.zeros(N, dtype=X.dtype)
    if grad is None:
        g_q = None
        gargs = (False, np.zeros(1, Xn.dtype), 1, np.zeros(1, np.int64), np.zeros(1, np.bool_))
        gargs += (np.zeros((1, 3, 1), Xn.dtype), np.zeros((1, 3, 1), Xn.dtype), np.zeros((1, 1), Xn.dtype))
    else:
        kin, ww, chain = grad
        g_q = torch.zeros(N, chain.dof, dtype=X.dtype)
        gargs = (True, ww.detach().contiguous().numpy(), ww.shape[0], chain.point_joint, chain.revolute)
        gargs += (kin.origins_t.numpy(), kin.axes_t.numpy(), g_q.numpy())
    ranges = column_ranges(N)
    out = [np.empty((3, c1 - c0), np.int64) for c0, c1 in ranges]
    m = [0] * len(ranges)

    def one(k: int, c0: int, c1: int) -> None:
        m[k] = _self_pass(Xn, c0, c1, *args, pen.numpy(), out[k][0], out[k][1], out[k][2], *gargs)

    run_columns(one, ranges)
    cfg, bi, bj = torch.from_numpy(np.concatenate([o[:, :mk] for o, mk in zip(out, m)], axis=1))
    return pen, cfg, bi, bj, g_q


def _parity(dtype: torch.dtype):
    from mpd.costs.base import cost_parity

    # a trajectory's value sums its configurations' terms in another order than torch's reduction
    tol = {"rtol": 2e-5, "atol": 1e-6} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    return cost_parity("self_collision", dtype, 32), tol


kernels.register(
    kernels.Kernel(
        "self_collision", __name__, "mpd.costs.self_collision.SelfCollisionCost.__call__ (the torch lines)", _parity
    )
)
