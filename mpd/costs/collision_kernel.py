"""Compiled fast path of the environment collision cost on the CPU (nearest-node grid SDF).

The torch path of :class:`mpd.costs.collision.CollisionCost` makes about a dozen passes over the (S, N) sphere x
configuration grid (node index, gather, the minimum over the fixed and the extra objects, ReLU, the activity mask,
the per-point weights, the (S, 3, N) gradient), each a full read of it. This
kernel does them in one compiled pass (numba, ``cache=True``): for each sphere centre it finds the nearest grid node
of each object set exactly as :func:`mpd.costs.sdf._nearest` does, keeps the closer set (the extra one only when
strictly closer), and writes the depth inside the margin-inflated obstacles into the trajectory's cost and, where
positive, ``coef * grad sdf`` into the centre gradient. It reads the grid's rows from a near table
(:func:`near_tables`): a bit per node and the rows of the nodes near an object only (4 % of EnvSpheres3D's nodes),
which stay in the second-level cache where the whole table (12 MB) did not. The Jacobian product's per-frame sums
(the gradients and their moments c x g) are accumulated in the same pass (no (S, 3, N) gradient array); the
joint-axis products stay torch's (:meth:`mpd.robots.chain.Chain.vjp_from_forces`).

The kernel ``collision`` of :mod:`mpd.kernels`. ``tests/test_costs.py`` pins it to the torch path (values,
gradients, the active count) on points inside, on the boundary of and outside the grid boxes, with and without extra
objects.
"""

from __future__ import annotations

import weakref
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from numba import njit

from mpd import kernels
from mpd.envs.grid import GridSDF


@njit(cache=True, nogil=True)
def _nodes(X, s, c0, c1, zscale, lo, hi, cell, nmax, kmin, kmax, step, clamp, idx, out):
    """Row of the nearest node (``idx[c - c0]``) and the distance to the grid box (``out[c - c0]``) of sphere s's
    centres in the columns c0 <= c < c1. The node is found in the whole grid's coordinates (``lo``, ``nmax``) and
    read from the table's block ``kmin .. kmax`` of it (``step``: the block's strides, int32).

    The table's constants are read into locals and the clamping decided outside the loops: loops of loads, divisions
    and roundings only, which the compiler vectorizes (reading them per element inside a loop with a run-time
    ``clamp`` kept it scalar: 4x slower)."""
    lo0, lo1, lo2 = lo[0], lo[1], lo[2]
    n0, n1, n2 = nmax[0], nmax[1], nmax[2]
    a0, a1, a2 = kmin[0], kmin[1], kmin[2]
    b0, b1, b2 = kmax[0], kmax[1], kmax[2]
    s0, s1, s2 = step[0], step[1], step[2]
    xs0, xs1, xs2 = X[s, 0, c0:c1], X[s, 1, c0:c1], X[s, 2, c0:c1]
    if clamp:
        hi0, hi1, hi2 = hi[0], hi[1], hi[2]
        for k in range(c1 - c0):
            x0 = xs0[k]
            x1 = xs1[k]
            x2 = xs2[k] * zscale
            p0 = min(max(x0, lo0), hi0)
            p1 = min(max(x1, lo1), hi1)
            p2 = min(max(x2, lo2), hi2)
            u0 = np.int32(min(max(min(np.rint((p0 - lo0) / cell), n0), a0), b0) - a0)
            u1 = np.int32(min(max(min(np.rint((p1 - lo1) / cell), n1), a1), b1) - a1)
            u2 = np.int32(min(max(min(np.rint((p2 - lo2) / cell), n2), a2), b2) - a2)
            idx[k] = u0 * s0 + u1 * s1 + u2 * s2
            out[k] = np.sqrt((x0 - p0) * (x0 - p0) + (x1 - p1) * (x1 - p1) + (x2 - p2) * (x2 - p2))
    else:
        for k in range(c1 - c0):
            u0 = np.int32(min(max(min(np.rint((xs0[k] - lo0) / cell), n0), a0), b0) - a0)
            u1 = np.int32(min(max(min(np.rint((xs1[k] - lo1) / cell), n1), a1), b1) - a1)
            u2 = np.int32(min(max(min(np.rint((xs2[k] * zscale - lo2) / cell), n2), a2), b2) - a2)
            idx[k] = u0 * s0 + u1 * s1 + u2 * s2


@njit(cache=True, nogil=True)
def _rank(bits, prefix, i):
    """The number of set bits before bit i (node i's row in the near table): the words' prefix count plus the
    population count of the word's lower bits (the shift-and-add form, which the compiler turns into popcnt)."""
    x = bits[i >> 5] & ((np.uint32(1) << np.uint32(i & 31)) - np.uint32(1))
    x = x - ((x >> np.uint32(1)) & np.uint32(0x55555555))
    x = (x & np.uint32(0x33333333)) + ((x >> np.uint32(2)) & np.uint32(0x33333333))
    x = (x + (x >> np.uint32(4))) & np.uint32(0x0F0F0F0F)
    # (numba widens the arithmetic to 64 bits: the byte sum is bits 24..31 of the product, masked)
    return prefix[i >> 5] + np.int32(((x * np.uint32(0x01010101)) >> np.uint32(24)) & np.uint32(0xFF))


@njit(cache=True, nogil=True)
def _collision_pass(
    X,
    c0,
    c1,
    zscale,
    r,
    w,
    coef,
    grid_a,
    grid_b,
    n_grids,
    near_a,
    near_b,
    clamp,
    frame,
    use_h,
    value,
    H,
    jac,
    Gq,
    rows,
    flat,
    counts,
    cap,
):
    """One pass over the columns c0 .. c1 - 1 of the (S, N) grid of sphere centres X (S, 3, N), a sphere (row of
    centres) at a time.

    ``grid_a``, ``grid_b``: the lookup tables (:func:`lookup_tables`: distances, gradients, lo, hi, cell, nmax,
    kmin, kmax, step) of the fixed and the extra objects (``n_grids`` = 1: only ``grid_a`` is read, the fixed
    objects' or both sets merged), whose node geometry this pass reads; ``near_a``, ``near_b``: their near tables
    (:func:`near_tables`: a bit per node, the words' prefix counts, the near nodes' distances and gradients), the
    only rows it reads. Each lookup is ``GridSDF.query(x, "nearest")``: the point clamped into the box (``clamp``;
    False when every point is known to lie inside), the nearest node's row, the point's distance to the box added.
    2-D grids are stored as 3-D ones of one layer, and ``zscale`` = 0 drops the points' z. ``r`` (S,): radius +
    margin; ``w`` (N,): quadrature weight of each configuration's trajectory point; ``coef``: -weight. Adds to
    ``value`` (N,) (sum over spheres of relu(r - d) w); writes the active entries ``flat[:E]`` (s * N + c, in order,
    ``counts[s]`` of them for sphere s) and their centre gradients ``coef w grad sdf`` as ``rows[:E]`` (E, 3), as long
    as E <= ``cap`` (beyond, entries are only counted); returns E. With ``use_h`` = 1 it also adds each active
    gradient g and its moment c x g about the origin (c the sphere's centre) to the sums of its sphere's frame,
    ``H[f - 1, 0, :, c] += g``, ``H[f - 1, 1, :, c] += c x g`` (``frame[s]`` = f, 0 = the root, which no joint
    moves): the Jacobian product then needs no (S, 3, N) gradient array
    (:meth:`mpd.robots.chain.Chain.vjp_from_forces`); with ``use_h`` = 2 (a chain without revolute joints, whose
    points' Jacobians ``jac`` (S, 3, dof) are constants) it adds J_s^T g to the joints' gradient ``Gq[c]`` (N, dof)
    instead. Disjoint column ranges can run at once (threads): they write disjoint entries.

    Per sphere in simple loops: node rows (vectorized), then a bit per entry (a table that stays in the second-level
    cache) rules out every entry whose node is not near an object (its distance is then at least the largest
    sphere's r: no cost, no gradient, exactly); only the rest, listed in order, read their distances and, where
    active, gradients from the near table (the near nodes only, in node order: 4 % of EnvSpheres3D's nodes, 0.45 MB
    of distances instead of 12 MB), at the rank of their bit. A set whose bit is clear counts as infinitely far: its
    true distance is at least the largest r, so the minimum, the active entries and which set's gradient is taken
    (the extra set's only where strictly closer) are those of the true distances.
    """
    S = X.shape[0]
    N = X.shape[2]
    n = c1 - c0
    _, _, loa, hia, cella, nmaxa, kmina, kmaxa, stepa = grid_a
    _, _, lob, hib, cellb, nmaxb, kminb, kmaxb, stepb = grid_b
    bits_a, pre_a, da, ga = near_a
    bits_b, pre_b, db, gb = near_b
    inf = X.dtype.type(np.inf)
    # buffers of the column range, indexed c - c0
    ia = np.empty(n, np.int32)
    ib = np.empty(n, np.int32)
    oa = np.zeros(n, X.dtype)
    ob = np.zeros(n, X.dtype)
    d = np.empty(n, X.dtype)
    ja = np.empty(n, np.int64)
    jb = np.empty(n, np.int64)
    use_b = np.zeros(n, np.bool_)
    near = np.empty(n, np.int32)
    active = 0
    for s in range(S):
        rs = r[s]
        _nodes(X, s, c0, c1, zscale, loa, hia, cella, nmaxa, kmina, kmaxa, stepa, clamp, ia, oa)
        if n_grids > 1:
            _nodes(X, s, c0, c1, zscale, lob, hib, cellb, nmaxb, kminb, kmaxb, stepb, clamp, ib, ob)
        # the entries whose node (of either set) is near an object, in order
        m = 0
        if n_grids > 1:
            for k in range(n):
                near[m] = k
                m += ((bits_a[ia[k] >> 5] >> (ia[k] & 31)) | (bits_b[ib[k] >> 5] >> (ib[k] & 31))) & 1
        else:
            for k in range(n):
                near[m] = k
                m += (bits_a[ia[k] >> 5] >> (ia[k] & 31)) & 1
        if n_grids > 1:  # extra objects: only where strictly closer
            for t in range(m):
                k = near[t]
                if (bits_a[ia[k] >> 5] >> (ia[k] & 31)) & 1:
                    ja[t] = _rank(bits_a, pre_a, ia[k])
                    d[t] = da[ja[t]] + oa[k]
                else:
                    d[t] = inf
                if (bits_b[ib[k] >> 5] >> (ib[k] & 31)) & 1:
                    jb[t] = _rank(bits_b, pre_b, ib[k])
                    e = db[jb[t]] + ob[k]
                else:
                    e = inf
                use_b[t] = e < d[t]
                d[t] = min(e, d[t])
        else:
            for t in range(m):
                ja[t] = _rank(bits_a, pre_a, ia[near[t]])
            for t in range(m):
                d[t] = da[ja[t]] + oa[near[t]]
        for t in range(m):
            k = near[t]
            value[c0 + k] += max(rs - d[t], 0) * w[c0 + k]
        before = active
        fs = frame[s]
        for t in range(m):
            if rs - d[t] > 0:
                k = near[t]
                c = c0 + k
                f = coef * w[c]
                if n_grids > 1 and use_b[t]:
                    g0 = f * gb[jb[t], 0]
                    g1 = f * gb[jb[t], 1]
                    g2 = f * gb[jb[t], 2]
                else:
                    j = ja[t]
                    g0 = f * ga[j, 0]
                    g1 = f * ga[j, 1]
                    g2 = f * ga[j, 2]
                if active < cap:
                    rows[active, 0] = g0
                    rows[active, 1] = g1
                    rows[active, 2] = g2
                    flat[active] = s * N + c
                if use_h == 2:  # constant point Jacobians: straight to the joints
                    for j in range(jac.shape[2]):
                        Gq[c, j] += jac[s, 0, j] * g0 + jac[s, 1, j] * g1 + jac[s, 2, j] * g2
                elif use_h == 1 and fs > 0:
                    x0, x1, x2 = X[s, 0, c], X[s, 1, c], X[s, 2, c]
                    H[fs - 1, 0, 0, c] += g0
                    H[fs - 1, 0, 1, c] += g1
                    H[fs - 1, 0, 2, c] += g2
                    H[fs - 1, 1, 0, c] += x1 * g2 - x2 * g1
                    H[fs - 1, 1, 1, c] += x2 * g0 - x0 * g2
                    H[fs - 1, 1, 2, c] += x0 * g1 - x1 * g0
                active += 1
        counts[s] = active - before
    return active


def _padded(grid: GridSDF, dtype: torch.dtype) -> tuple[torch.Tensor, np.ndarray, np.ndarray, list[int]]:
    """The grid's packed rows (nodes, 4) as a 3-D grid (a 2-D grid: one layer at z = 0 with a zero z gradient), its
    lo and hi (3,) and its shape (3 entries)."""
    packed, lo, hi, _, _ = grid.consts(dtype, "cpu")
    lo, hi = lo.numpy(), hi.numpy()
    D = grid.dim
    if D < 3:  # the kernel has one 3-D path
        packed = torch.cat([packed, packed.new_zeros(packed.shape[0], 4 - packed.shape[1])], 1)
        pad = np.zeros(3 - D, dtype=lo.dtype)
        lo, hi = np.concatenate([lo, pad]), np.concatenate([hi, pad])
    return packed, lo, hi, list(grid.shape) + [1] * (3 - D)


def _block(grid: GridSDF, reach: float | None) -> tuple[np.ndarray, np.ndarray]:
    """The node range kmin .. kmax (3,) that contains the nearest node of every point within ``reach`` of the origin
    (one node of slack each side for rounding); the whole grid when ``reach`` is None."""
    shape = np.array(list(grid.shape) + [1] * (3 - grid.dim))
    kmin, kmax = np.zeros(3, np.int64), shape - 1
    if reach is not None:
        D = grid.dim
        kmin[:D] = np.maximum(0, np.floor((-reach - grid.lo) / grid.cell).astype(np.int64) - 1)
        kmax[:D] = np.minimum(shape[:D] - 1, np.ceil((reach - grid.lo) / grid.cell).astype(np.int64) + 1)
    return kmin, kmax


def _block_rows(packed: torch.Tensor, shape: list[int], kmin: np.ndarray, kmax: np.ndarray) -> torch.Tensor:
    """The rows (nodes, 4) of the grid's nodes kmin .. kmax, in the grid's order."""
    return packed.view(*shape, 4)[tuple(slice(a, b + 1) for a, b in zip(kmin, kmax))].reshape(-1, 4)


def _table(rows: torch.Tensor, lo, hi, shape, cell: float, kmin: np.ndarray, kmax: np.ndarray) -> tuple:
    """A kernel lookup table from the rows of the block kmin .. kmax of a grid of ``shape``: its distances
    (contiguous) and gradients apart, and what locates a node in it."""
    # the node index is accumulated in int32 (exact: the block has fewer than 2^31 nodes)
    bshape = kmax - kmin + 1
    if np.prod(bshape) >= 2**31:
        raise ValueError(f"a grid block of {bshape.tolist()} nodes is too large for the collision kernel (2^31 nodes)")
    step = np.array([np.prod(bshape[k + 1 :]) for k in range(3)], dtype=np.int32)
    dt = lo.dtype
    return (
        np.ascontiguousarray(rows[:, 0].numpy()),
        np.ascontiguousarray(rows[:, 1:].numpy()),
        lo,
        hi,
        dt.type(cell),
        np.array([float(n - 1) for n in shape], dtype=dt),
        kmin.astype(dt),
        kmax.astype(dt),
        step,
    )


_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # env -> {(dtype, reach): (tables, clamp)}


def lookup_tables(env, dtype: torch.dtype, reach: float | None) -> tuple[list[tuple], bool]:
    """The kernel's lookup tables of the environment's object sets and whether points need clamping into the grid
    box (False when ``reach`` is known and every grid box contains the ball of that radius).

    Made once per environment, dtype and reach. Two grids of the same nodes (the fixed and the extra objects'
    grids share the environment's box) are merged into one table that holds, per node, the extra objects' row
    where its distance is strictly smaller, else the fixed objects' (the rule of two lookups, so the same result
    with half the reads; not when points are clamped). When no point needs clamping, each table keeps only the
    block of nodes that can be nearest to a point within ``reach`` (EnvSpheres3D-RobotPanda: 145^3 of the 201^3
    nodes): its distances fit this CPU's last-level cache."""
    key = (dtype, reach)
    per_env = _TABLES.setdefault(env, {})
    if key in per_env:
        return per_env[key]
    grids = [
        env.grid(name) for name, objs in (("fixed", env.fixed), ("extra", env.extra)) if objs is not None and len(objs)
    ]
    clamp = reach is None or not all(bool((g.lo <= -reach).all() and (g.hi >= reach).all()) for g in grids)
    padded = [_padded(g, dtype) for g in grids]
    blocks = [_block(g, None if clamp else reach) for g in grids]
    # merged only without clamping: a point's distance to the box, added to both sets' distances, could round
    # two unequal distances to equal ones, where the rule keeps the fixed objects' gradient
    same = len(grids) == 2 and grids[0].shape == grids[1].shape and grids[0].cell == grids[1].cell
    if same and not clamp and np.array_equal(grids[0].lo, grids[1].lo):
        g0 = grids[0]
        (pa, lo, hi, shape), (pb, _, _, _) = padded
        a, b = (_block_rows(p, shape, *blocks[0]) for p in (pa, pb))
        tables = [_table(torch.where((b[:, 0] < a[:, 0])[:, None], b, a), lo, hi, shape, g0.cell, *blocks[0])]
    else:
        tables = [
            _table(_block_rows(p, shape, *blk), lo, hi, shape, g.cell, *blk)
            for (p, lo, hi, shape), g, blk in zip(padded, grids, blocks)
        ]
    per_env[key] = (tables, clamp)
    return tables, clamp


_NEAR: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # env -> {(dtype, reach, threshold): near tables}


def near_tables(env, grids: list[tuple], dtype: torch.dtype, reach: float | None, threshold) -> list[tuple]:
    """Per lookup table, its near table: (one bit per node (uint32 words, node i in bit i % 32 of word i // 32), set
    where the node's distance is below ``threshold`` (the largest radius + margin of the spheres); the number of set
    bits before each word (int32); the distances (K,) and gradients (K, 3) of the K near nodes, in node order). A
    sphere whose nearest node's bit is clear is at least its radius + margin from every object of that set (a point
    outside the grid box only adds its distance to the box): the kernel skips it, and reads the rows of the others at
    their bit's rank. Made once per table and threshold."""
    key = (dtype, reach, float(threshold))
    per_env = _NEAR.setdefault(env, {})
    if key not in per_env:
        out = []
        for dist, grad, *_ in grids:
            near = np.zeros(-(-dist.shape[0] // 32) * 32, np.bool_)
            near[: dist.shape[0]] = dist < dist.dtype.type(threshold)
            bits = np.packbits(near, bitorder="little").view("<u4").astype(np.uint32)
            per_word = near.reshape(-1, 32).sum(1)
            prefix = np.concatenate([[0], np.cumsum(per_word)[:-1]]).astype(np.int32)
            rows = np.flatnonzero(near[: dist.shape[0]])
            out.append((bits, prefix, np.ascontiguousarray(dist[rows]), np.ascontiguousarray(grad[rows])))
        per_env[key] = out
    return per_env[key]


def collision_pass(
    env,
    X: torch.Tensor,
    r: torch.Tensor,
    w: torch.Tensor,
    weight: float,
    reach: float | None = None,
    frames: tuple[np.ndarray, int] | None = None,
    max_entries: int | None = None,
    jacobian: np.ndarray | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
    """For centres X (S, 3, N): (per-configuration value (N,), active entries (E,) as s * N + c, their centre
    gradients (E, 3), the frames' sums H (dof, 2, 3, N), [sum g; sum c x g], or None); see the module docstring.
    The gradient of ``X[:, D:]`` is 0 for a D < 3 task. ``reach``: a bound of |x| (the robot's reach around the
    origin); when every grid box contains that ball, no point needs clamping. ``frames``: (the frame of each sphere,
    ``chain.point_joint + 1``, dof), to accumulate H (for :meth:`mpd.robots.chain.Chain.vjp_from_forces`).
    ``max_entries``: when there are more active entries than this, they are not returned (None, None in their
    place; H then carries the gradient): the dense case's (E, 3) rows are neither written nor allocated.
    ``jacobian``: the spheres' constant Jacobians (S, 3, dof) of a chain without revolute joints; the gradient
    w.r.t. each configuration's joints (N, dof) is then accumulated in the pass and returned in H's place."""
    S, _, N = X.shape
    D = env.dim
    grids, clamp = lookup_tables(env, X.dtype, reach)
    value = torch.zeros(N, dtype=X.dtype)
    if jacobian is not None:
        H = torch.zeros(N, jacobian.shape[2], dtype=X.dtype)
    elif frames is not None:
        H = torch.zeros(frames[1], 2, 3, N, dtype=X.dtype)
    else:
        H = None
    if not grids:
        return value, torch.empty(0, dtype=torch.int64), torch.empty(0, 3, dtype=X.dtype), H
    Xn = X.detach().contiguous().numpy()
    dt = Xn.dtype.type
    frame, Hn = np.zeros(S, np.int64), np.zeros((1, 2, 3, 1), Xn.dtype)
    jac, Gq, mode = np.zeros((1, 3, 1), Xn.dtype), np.zeros((1, 1), Xn.dtype), 0
    if jacobian is not None:
        jac, Gq, mode = np.ascontiguousarray(jacobian, dtype=Xn.dtype), H.numpy(), 2
    elif frames is not None:
        frame, Hn, mode = frames[0], H.numpy(), 1
    rn = r.detach().reshape(-1).contiguous().numpy()
    near = near_tables(env, grids, X.dtype, reach, rn.max())
    args = (
        dt(1.0 if D == 3 else 0.0),
        rn,
        w.detach().repeat(N // w.shape[0]).numpy(),
        dt(-weight),
        grids[0],
        grids[-1],
        len(grids),
        near[0],
        near[-1],
        clamp,
        frame,
        mode,
        value.numpy(),
        Hn,
        jac,
        Gq,
    )
    ranges = column_ranges(N)
    # each range's buffers hold up to max_entries (all of a range's entries could be the ones returned)
    caps = [S * (c1 - c0) if max_entries is None else min(S * (c1 - c0), max_entries) for c0, c1 in ranges]
    rows = [np.empty((cap, 3), Xn.dtype) for cap in caps]
    flats = [np.empty(cap, np.int64) for cap in caps]
    counts = [np.zeros(S, np.int64) for _ in ranges]
    run_columns(lambda k, c0, c1: _collision_pass(Xn, c0, c1, *args, rows[k], flats[k], counts[k], caps[k]), ranges)
    if max_entries is not None and sum(int(c.sum()) for c in counts) > max_entries:
        return value, None, None, H
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


# Columns per thread below which one thread does it all. Inside a plan on 2 cores, splitting a Panda batch (100 x
# 128 configurations) over two threads made each cost call slower, not faster (MPD plan 0.72-0.75 s with one thread
# against 0.74-0.83 s with two, alternating in one process): the pass reads memory more than it computes, and the
# second thread competes with torch's OpenMP workers, which spin after each parallel region. So only very large
# batches are split.
MIN_COLUMNS_PER_THREAD = 1 << 20
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


def _parity(dtype: torch.dtype):
    from mpd.costs.base import cost_parity

    return cost_parity("collision", dtype, 31), {"rtol": 1e-5, "atol": 1e-6}


kernels.register(
    kernels.Kernel("collision", __name__, "mpd.costs.collision.CollisionCost.__call__ (the torch lines)", _parity)
)
