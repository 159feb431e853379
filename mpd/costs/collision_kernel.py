"""Compiled fast path of the environment collision cost on the CPU (nearest-node grid SDF).

The torch path of :class:`mpd.costs.collision.CollisionCost` makes about a dozen passes over the (S, N) sphere x
configuration grid (node index, gather, the minimum over the fixed and the extra objects, ReLU, the activity mask,
the per-point weights, the (S, 3, N) gradient), ~15 ms for 100 Panda trajectories x 128 points on one core. This
kernel does them in one compiled pass (numba, ``cache=True``): for each sphere centre it finds the nearest grid node
of each object set exactly as :func:`mpd.costs.sdf._nearest` does, keeps the closer set (the extra one only when
strictly closer), and writes the depth inside the margin-inflated obstacles into the trajectory's cost and, where
positive, ``coef * grad sdf`` into the centre gradient. The Jacobian product's per-frame moments are accumulated
in the same pass (no (S, 3, N) gradient array); the joint-axis products stay torch's
(:meth:`mpd.robots.chain.Chain.vjp_from_moments`).

``tests/test_costs.py`` pins the kernel to the torch path (values, gradients, the active count) on points inside,
on the boundary of and outside the grid boxes, with and without extra objects.
"""

from __future__ import annotations

import weakref
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from numba import njit

from mpd.envs.grid import GridSDF


@njit(cache=True, nogil=True)
def _nodes(X, s, c0, c1, zscale, lo, hi, cell, nmax, step, clamp, idx, out):
    """Row of the nearest node (``idx[c - c0]``) and the distance to the grid box (``out[c - c0]``) of sphere s's
    centres in the columns c0 <= c < c1."""
    for c in range(c0, c1):
        x0 = X[s, 0, c]
        x1 = X[s, 1, c]
        x2 = X[s, 2, c] * zscale
        p0 = min(max(x0, lo[0]), hi[0]) if clamp else x0
        p1 = min(max(x1, lo[1]), hi[1]) if clamp else x1
        p2 = min(max(x2, lo[2]), hi[2]) if clamp else x2
        u0 = min(np.rint((p0 - lo[0]) / cell), nmax[0])
        u1 = min(np.rint((p1 - lo[1]) / cell), nmax[1])
        u2 = min(np.rint((p2 - lo[2]) / cell), nmax[2])
        idx[c - c0] = np.int32(u0 * step[0] + u1 * step[1] + u2 * step[2])
        if clamp:
            out[c - c0] = np.sqrt((x0 - p0) * (x0 - p0) + (x1 - p1) * (x1 - p1) + (x2 - p2) * (x2 - p2))


@njit(cache=True, nogil=True)
def _collision_pass(
    X, c0, c1, zscale, r, w, coef, grid_a, grid_b, n_grids, clamp, frame, lw, use_h, value, H, rows, flat, counts
):
    """One pass over the columns c0 .. c1 - 1 of the (S, N) grid of sphere centres X (S, 3, N), a sphere (row of
    centres) at a time.

    ``grid_a``, ``grid_b``: (packed, lo, hi, cell, nmax, step) of the fixed and the extra objects' grids (``n_grids``
    = 1: only ``grid_a`` is read). Each lookup is ``GridSDF.query(x, "nearest")``: the point clamped into the box
    (``clamp``; False when every point is known to lie inside), the nearest node's row, the point's distance to the
    box added. 2-D grids are stored as 3-D ones of one layer, and ``zscale`` = 0 drops the points' z. ``r`` (S,):
    radius + margin; ``w`` (N,): quadrature weight of each configuration's trajectory point; ``coef``: -weight.
    Adds to ``value`` (N,) (sum over spheres of relu(r - d) w); writes the active entries ``flat[:E]`` (s * N + c, in
    order, ``counts[s]`` of them for sphere s) and their centre gradients ``coef w grad sdf`` as ``rows[:E]`` (E, 3);
    returns E. With ``use_h`` it also adds each active gradient to the moments of its sphere's frame,
    ``H[f - 1, m, :, c] += lw[s, m] g`` (``frame[s]`` = f, 0 = the root, which no joint moves): the Jacobian
    product then needs no (S, 3, N) gradient array (:meth:`mpd.robots.chain.Chain.vjp_from_moments`). Disjoint
    column ranges can run at once (threads): they write disjoint entries.

    Per sphere in simple loops that the compiler vectorizes: node rows, the distance gather, the depth, then the
    few active entries (one loop with a data-dependent branch per entry was 5x slower).
    """
    S = X.shape[0]
    N = X.shape[2]
    n = c1 - c0
    pa, loa, hia, cella, nmaxa, stepa = grid_a
    pb, lob, hib, cellb, nmaxb, stepb = grid_b
    # buffers of the column range, indexed c - c0
    ia = np.empty(n, np.int32)
    ib = np.empty(n, np.int32)
    oa = np.zeros(n, X.dtype)
    ob = np.zeros(n, X.dtype)
    d = np.empty(n, X.dtype)
    use_b = np.zeros(n, np.bool_)
    active = 0
    for s in range(S):
        rs = r[s]
        _nodes(X, s, c0, c1, zscale, loa, hia, cella, nmaxa, stepa, clamp, ia, oa)
        for k in range(n):
            d[k] = pa[ia[k], 0] + oa[k]
        if n_grids > 1:  # extra objects: only where strictly closer
            _nodes(X, s, c0, c1, zscale, lob, hib, cellb, nmaxb, stepb, clamp, ib, ob)
            for k in range(n):
                e = pb[ib[k], 0] + ob[k]
                use_b[k] = e < d[k]
                d[k] = min(e, d[k])
        for k in range(n):
            value[c0 + k] += max(rs - d[k], 0) * w[c0 + k]
        before = active
        fs = frame[s]
        for k in range(n):
            if rs - d[k] > 0:
                c = c0 + k
                f = coef * w[c]
                if n_grids > 1 and use_b[k]:
                    g0 = f * pb[ib[k], 1]
                    g1 = f * pb[ib[k], 2]
                    g2 = f * pb[ib[k], 3]
                else:
                    g0 = f * pa[ia[k], 1]
                    g1 = f * pa[ia[k], 2]
                    g2 = f * pa[ia[k], 3]
                rows[active, 0] = g0
                rows[active, 1] = g1
                rows[active, 2] = g2
                if use_h and fs > 0:
                    for m in range(4):
                        H[fs - 1, m, 0, c] += lw[s, m] * g0
                        H[fs - 1, m, 1, c] += lw[s, m] * g1
                        H[fs - 1, m, 2, c] += lw[s, m] * g2
                flat[active] = s * N + c
                active += 1
        counts[s] = active - before
    return active


def _grid_args(grid: GridSDF, dtype: torch.dtype) -> tuple:
    packed, lo, hi, _, _ = grid._consts(dtype, "cpu")
    packed, lo, hi = packed.numpy(), lo.numpy(), hi.numpy()
    D = grid.dim
    if D < 3:  # one layer at z = 0 with a zero z gradient: the kernel has one 3-D path
        packed = np.concatenate([packed, np.zeros((packed.shape[0], 4 - packed.shape[1]), packed.dtype)], axis=1)
        pad = np.zeros(3 - D, dtype=lo.dtype)
        lo, hi = np.concatenate([lo, pad]), np.concatenate([hi, pad])
    shape = list(grid.shape) + [1] * (3 - D)
    # the node index is accumulated in float64: exact for any grid
    step = np.array([float(np.prod(shape[k + 1 :])) for k in range(3)])
    nmax = np.array([float(n - 1) for n in shape], dtype=lo.dtype)
    return (np.ascontiguousarray(packed), lo, hi, lo.dtype.type(grid.cell), nmax, step)


_ARGS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # grid -> {dtype: kernel arguments}


def supported(X: torch.Tensor) -> bool:
    """The kernel handles CPU float32 / float64 tensors that need no autograd."""
    return X.device.type == "cpu" and X.dtype in (torch.float32, torch.float64) and not X.requires_grad


def collision_pass(
    env,
    X: torch.Tensor,
    r: torch.Tensor,
    w: torch.Tensor,
    weight: float,
    reach: float | None = None,
    moments: tuple[np.ndarray, np.ndarray, int] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """For centres X (S, 3, N): (per-configuration value (N,), active entries (E,) as s * N + c, their centre
    gradients (E, 3), the frames' moments H (dof, 4, 3, N) or None); see the module docstring. ``X[:, D:]`` is
    ignored for a D < 3 task (its gradient rows are 0). ``reach``: a bound of |x| (the robot's reach around the
    origin); when every grid box contains that ball, no point needs clamping. ``moments``: (frame of each sphere,
    its [l; 1] weights, dof) from :meth:`mpd.robots.chain.Chain.point_moments_weights`, to accumulate H."""
    S, _, N = X.shape
    D = env.dim
    grids = []
    clamp = False
    for name, objs in (("fixed", env.fixed), ("extra", env.extra)):
        if objs is None or not len(objs):
            continue
        grid = env.grid(name)
        clamp = clamp or reach is None or not bool((grid.lo <= -reach).all() and (grid.hi >= reach).all())
        per_dtype = _ARGS.setdefault(grid, {})
        if X.dtype not in per_dtype:
            per_dtype[X.dtype] = _grid_args(grid, X.dtype)
        grids.append(per_dtype[X.dtype])
    value = torch.zeros(N, dtype=X.dtype)
    H = torch.zeros(moments[2], 4, 3, N, dtype=X.dtype) if moments is not None else None
    if not grids:
        return value, torch.empty(0, dtype=torch.int64), torch.empty(0, 3, dtype=X.dtype), H
    Xn = X.detach().contiguous().numpy()
    dt = Xn.dtype.type
    if moments is not None:
        frame, lw = moments[0], moments[1].astype(Xn.dtype, copy=False)
        Hn = H.numpy()
    else:
        frame, lw, Hn = np.zeros(S, np.int64), np.zeros((S, 4), Xn.dtype), np.zeros((1, 4, 3, 1), Xn.dtype)
    args = (
        dt(1.0 if D == 3 else 0.0),
        r.detach().reshape(-1).contiguous().numpy(),
        w.detach().repeat(N // w.shape[0]).numpy(),
        dt(-weight),
        grids[0],
        grids[-1],
        len(grids),
        clamp,
        frame,
        lw,
        moments is not None,
        value.numpy(),
        Hn,
    )
    ranges = column_ranges(N)
    rows = [np.empty((S * (c1 - c0), 3), Xn.dtype) for c0, c1 in ranges]
    flats = [np.empty(S * (c1 - c0), np.int64) for c0, c1 in ranges]
    counts = [np.zeros(S, np.int64) for _ in ranges]
    run_columns(lambda k, c0, c1: _collision_pass(Xn, c0, c1, *args, rows[k], flats[k], counts[k]), ranges)
    if len(ranges) == 1:
        e = int(counts[0].sum())
        return value, torch.from_numpy(flats[0][:e]), torch.from_numpy(rows[0][:e]), H
    # the ranges' entries interleaved sphere by sphere: the order of one pass over all columns
    fparts, rparts = [], []
    starts = [np.concatenate([[0], np.cumsum(c)]) for c in counts]
    for s in range(S):
        for f, g, st in zip(flats, rows, starts):
            fparts.append(f[st[s] : st[s + 1]])
            rparts.append(g[st[s] : st[s + 1]])
    return value, torch.from_numpy(np.concatenate(fparts)), torch.from_numpy(np.concatenate(rparts)), H


# columns per thread below which one thread does it all (thread start-up costs ~50 us)
MIN_COLUMNS_PER_THREAD = 2048
_POOL: dict[int, ThreadPoolExecutor] = {}


def column_ranges(N: int) -> list[tuple[int, int]]:
    """Split N configurations into one contiguous range per torch intra-op thread (the compiled passes release the
    GIL, so the ranges run in parallel threads); one range for small batches. The results do not depend on the
    split: each configuration is computed by one thread, in the same order."""
    n = max(1, min(torch.get_num_threads(), N // MIN_COLUMNS_PER_THREAD))
    edges = [round(k * N / n) for k in range(n + 1)]
    return [(edges[k], edges[k + 1]) for k in range(n)]


def run_columns(fn, ranges: list[tuple[int, int]]) -> None:
    """fn(k, c0, c1) for each range k, in a pool of threads when there is more than one."""
    if len(ranges) == 1:
        fn(0, *ranges[0])
        return
    pool = _POOL.get(len(ranges))
    if pool is None:
        pool = _POOL[len(ranges)] = ThreadPoolExecutor(len(ranges) - 1, thread_name_prefix="mpd-cost")
    futures = [pool.submit(fn, k, c0, c1) for k, (c0, c1) in enumerate(ranges) if k > 0]
    fn(0, *ranges[0])  # this thread takes the first range
    for f in futures:
        f.result()
