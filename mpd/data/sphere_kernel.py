"""Compiled validity of configurations under the sphere model: the fast path of :class:`SphereChecker`.

The planner asks about one state or one short edge at a time. In numpy each such call is mostly
per-operation overhead for the Panda (7 joints x a few small array operations, two SDF passes); this module
does the same computation per state in one compiled loop (numba, ``cache=True``) and stops at the first
colliding state, so an edge in collision usually costs a few states. The arithmetic is the numpy checker's:
forward kinematics by the chain's Rodrigues terms, per-link bounding spheres for culling, the analytic SDF of
spheres and rounded boxes, self-collision sphere pairs behind link-pair culling. Only the summation order of a
few dot products differs, so a state exactly on the clearance boundary (to ~1e-15) may be judged differently;
``tests/test_data.py`` pins the two implementations to each other on states all over each task's scene. The kernel
``sphere`` of :mod:`mpd.kernels` (its ``torch`` mode: the numpy checker).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from mpd import kernels

if TYPE_CHECKING:
    from mpd.robots.chain import ChainArrays


@njit(cache=True, nogil=True)
def _point(frames, f, local, out, flat):
    """out = R_f local + p_f (z = 0 for a planar task, ``flat``)."""
    for a in range(3):
        out[a] = frames[f, a, 0] * local[0] + frames[f, a, 1] * local[1] + frames[f, a, 2] * local[2] + frames[f, a, 3]
    if flat:
        out[2] = 0.0


@njit(cache=True, nogil=True)
def _sdf_one(x, o, obs_c, obs_r, box_r, box_crot, box_h, corner) -> float:
    """Signed distance of a point to obstacle o: the spheres first, then the rounded boxes (all in 3-D; a planar
    task's obstacles lie in z = 0 with boxes unbounded along z)."""
    ns = obs_r.shape[0]
    if o < ns:
        d0 = x[0] - obs_c[0, o]
        d1 = x[1] - obs_c[1, o]
        d2 = x[2] - obs_c[2, o]
        return math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - obs_r[o]
    n = o - ns
    out2 = 0.0
    inside = -np.inf
    for k in range(3):
        loc = x[0] * box_r[0, k, n] + x[1] * box_r[1, k, n] + x[2] * box_r[2, k, n] - box_crot[k, n]
        qd = abs(loc) - box_h[k, n]
        pos = max(qd, 0.0)
        out2 += pos * pos
        inside = max(inside, qd)
    return math.sqrt(out2) + min(inside, 0.0) - corner


@njit(cache=True, nogil=True)
def _sdf_all(x, obs_c, obs_r, box_r, box_crot, box_h, corner, dist) -> None:
    """dist[o] = signed distance of a point to each obstacle o (branch-free loops over obstacles: vectorised)."""
    ns = obs_r.shape[0]
    nb = box_h.shape[1]
    for o in range(ns):
        d0 = x[0] - obs_c[0, o]
        d1 = x[1] - obs_c[1, o]
        d2 = x[2] - obs_c[2, o]
        dist[o] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - obs_r[o]
    for n in range(nb):
        q0 = abs(x[0] * box_r[0, 0, n] + x[1] * box_r[1, 0, n] + x[2] * box_r[2, 0, n] - box_crot[0, n]) - box_h[0, n]
        q1 = abs(x[0] * box_r[0, 1, n] + x[1] * box_r[1, 1, n] + x[2] * box_r[2, 1, n] - box_crot[1, n]) - box_h[1, n]
        q2 = abs(x[0] * box_r[0, 2, n] + x[1] * box_r[1, 2, n] + x[2] * box_r[2, 2, n] - box_crot[2, n]) - box_h[2, n]
        p0 = max(q0, 0.0)
        p1 = max(q1, 0.0)
        p2 = max(q2, 0.0)
        dist[ns + n] = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2) + min(max(max(q0, q1), q2), 0.0) - corner


@njit(cache=True, nogil=True)
def _state_ok(
    q,  # (dof,)
    revolute,  # (dof,) bool
    rot_terms,  # (dof, 3, 9)
    axis_off,  # (dof, 3, 2)
    off_r,  # (dof, 3, 3)
    axes,  # (dof, 3)
    sph_frame,  # (S,) frame index (0 = root)
    sph_local,  # (S, 3)
    thresh,  # (S,) radius + clearance
    link_ptr,  # (L + 1,) spheres of link l: link_sph[link_ptr[l]:link_ptr[l + 1]]
    link_sph,  # (S,)
    link_frame,  # (L,)
    link_mid,  # (L, 3)
    link_r,  # (L,) bounding radius + clearance (the culling threshold)
    cull,  # bool
    obs_c,  # (3, Ns) obstacle sphere centres
    obs_r,  # (Ns,)
    box_r,  # (3, 3, Nb) rotations [a, k, n] (columns: box axes)
    box_crot,  # (3, Nb) c_n^T R_n
    box_h,  # (3, Nb) half sizes minus the corner radius
    corner,  # float
    pairs,  # (P, 2) self-collision sphere pairs, grouped by link pair
    pair_r2,  # (P,)
    lpair_ptr,  # (K + 1,) pairs of link pair k: pairs[lpair_ptr[k]:lpair_ptr[k + 1]]
    lpairs,  # (K, 2)
    lpair_r2,  # (K,)
    flat,  # bool: a planar task (z = 0)
    frames,  # (dof + 1, 3, 4) scratch
    centres,  # (S, 3) scratch
    link_b,  # (L, 3) scratch
    done,  # (S,) scratch: centre computed
    oo,  # (3,) scratch: a joint's origin
    dist,  # (obstacles,) scratch
) -> bool:
    dof = q.shape[0]
    # ---- forward kinematics: frames[f] = [R | p] of frame f (0 = root), the chain's Rodrigues terms
    for a in range(3):
        for b in range(3):
            frames[0, a, b] = 1.0 if a == b else 0.0
        frames[0, a, 3] = 0.0
    for j in range(dof):
        for a in range(3):  # o = p + R @ axis_off[j][:, 1]
            oo[a] = frames[j, a, 3] + (
                frames[j, a, 0] * axis_off[j, 0, 1]
                + frames[j, a, 1] * axis_off[j, 1, 1]
                + frames[j, a, 2] * axis_off[j, 2, 1]
            )
        if revolute[j]:
            s = math.sin(q[j])
            co = 1.0 - math.cos(q[j])
            for a in range(3):
                r0 = frames[j, a, 0]
                r1 = frames[j, a, 1]
                r2 = frames[j, a, 2]
                for b in range(3):
                    t0 = r0 * rot_terms[j, 0, b] + r1 * rot_terms[j, 1, b] + r2 * rot_terms[j, 2, b]
                    t1 = r0 * rot_terms[j, 0, 3 + b] + r1 * rot_terms[j, 1, 3 + b] + r2 * rot_terms[j, 2, 3 + b]
                    t2 = r0 * rot_terms[j, 0, 6 + b] + r1 * rot_terms[j, 1, 6 + b] + r2 * rot_terms[j, 2, 6 + b]
                    frames[j + 1, a, b] = t0 + s * t1 + co * t2
                frames[j + 1, a, 3] = oo[a]
        else:
            for a in range(3):
                for b in range(3):
                    frames[j + 1, a, b] = (
                        frames[j, a, 0] * off_r[j, 0, b]
                        + frames[j, a, 1] * off_r[j, 1, b]
                        + frames[j, a, 2] * off_r[j, 2, b]
                    )
            for a in range(3):
                ax = (
                    frames[j + 1, a, 0] * axes[j, 0]
                    + frames[j + 1, a, 1] * axes[j, 1]
                    + frames[j + 1, a, 2] * axes[j, 2]
                )
                frames[j + 1, a, 3] = oo[a] + ax * q[j]
    S = sph_frame.shape[0]
    L = link_frame.shape[0]
    No = obs_r.shape[0] + box_h.shape[1]
    for s_ in range(S):
        done[s_] = False
    # ---- environment. With culling, each link's bounding sphere is checked against every obstacle first: the SDF
    # is 1-Lipschitz, so a sphere of the link can only come closer than its threshold to an obstacle that the
    # bounding sphere comes closer to than its radius plus the clearance; the link's spheres are then checked
    # against those obstacles only.
    for l_ in range(L):
        if cull:
            _point(frames, link_frame[l_], link_mid[l_], link_b[l_], flat)
            _sdf_all(link_b[l_], obs_c, obs_r, box_r, box_crot, box_h, corner, dist)
            any_near = False
            for o in range(No):
                if dist[o] <= link_r[l_]:
                    any_near = True
            if not any_near:
                continue
        for i in range(link_ptr[l_], link_ptr[l_ + 1]):
            s_ = link_sph[i]
            _point(frames, sph_frame[s_], sph_local[s_], centres[s_], flat)
            done[s_] = True
            for o in range(No):
                if cull and dist[o] > link_r[l_]:
                    continue
                if not _sdf_one(centres[s_], o, obs_c, obs_r, box_r, box_crot, box_h, corner) > thresh[s_]:
                    return False
    # ---- self collision: sphere pairs of the link pairs whose bounding spheres overlap
    K = lpairs.shape[0]
    for k in range(K):
        if cull:
            la = lpairs[k, 0]
            lb = lpairs[k, 1]
            if not cull_free(link_b, la, lb, lpair_r2[k]):
                continue
        for i in range(lpair_ptr[k], lpair_ptr[k + 1]):
            u = pairs[i, 0]
            v = pairs[i, 1]
            if not done[u]:
                _point(frames, sph_frame[u], sph_local[u], centres[u], flat)
                done[u] = True
            if not done[v]:
                _point(frames, sph_frame[v], sph_local[v], centres[v], flat)
                done[v] = True
            d0 = centres[u, 0] - centres[v, 0]
            d1 = centres[u, 1] - centres[v, 1]
            d2 = centres[u, 2] - centres[v, 2]
            if d0 * d0 + d1 * d1 + d2 * d2 < pair_r2[i]:
                return False
    return True


@njit(cache=True, nogil=True)
def cull_free(link_b, la, lb, r2) -> bool:
    """Whether the bounding spheres of links la and lb overlap (their sphere pairs need checking)."""
    d0 = link_b[la, 0] - link_b[lb, 0]
    d1 = link_b[la, 1] - link_b[lb, 1]
    d2 = link_b[la, 2] - link_b[lb, 2]
    return d0 * d0 + d1 * d1 + d2 * d2 < r2


@njit(cache=True, nogil=True)
def valid_states(q, c, out, stop_at_first) -> int:
    """Fill out[m] with the validity of q[m] (M, dof); return the first invalid index or -1. With
    ``stop_at_first`` the loop ends at the first invalid state (the rest of ``out`` is then undefined)."""
    first = -1
    for m in range(q.shape[0]):
        ok = _state_ok(q[m], *c)
        out[m] = ok
        if not ok and first < 0:
            first = m
            if stop_at_first:
                return first
    return first


@njit(cache=True, nogil=True)
def edge_valid(a, b, n, chunk, c) -> bool:
    """Whether every state a + (k / n)(b - a), k = 1..n, is valid (``edge_states``' grid), checked from the end
    state back in a coarse pass (every ``stride``-th state) and then the rest, stopping at the first hit."""
    stride = 1
    if n > chunk:
        stride = -(-n // chunk)
    q = np.empty(a.shape[0])
    d = b - a
    # reversed order: index r <-> k = n - r
    for r in range(0, n, stride):
        t = (n - r) / n
        for i in range(a.shape[0]):
            q[i] = a[i] + t * d[i]
        if not _state_ok(q, *c):
            return False
    if stride > 1:
        for r in range(n):
            if r % stride == 0:
                continue
            t = (n - r) / n
            for i in range(a.shape[0]):
                q[i] = a[i] + t * d[i]
            if not _state_ok(q, *c):
                return False
    return True


@dataclass(frozen=True)
class SphereInputs:
    """The arrays the kernels read, built by :meth:`mpd.data.checkers.SphereChecker.kernel_inputs` (contiguous
    float64 / int64 / bool; the scene in 3-D: a planar task's obstacles at z = 0, its boxes unbounded along z).

    ``chain``: the robot's constants (:meth:`mpd.robots.chain.KinematicChain.kernel_inputs`); per sphere its
    ``thresh`` (radius + clearance); per link the spheres ``link_sph[link_ptr[l]:link_ptr[l + 1]]``, its frame,
    bounding-sphere centre (in that frame) and culling threshold ``link_r``; ``cull``: whether links are culled; the
    obstacle spheres (centres (3, Ns), radii) and rounded boxes (rotations (3, 3, Nb), c_n^T R_n (3, Nb), half sizes
    minus the corner radius (3, Nb), the ``corner`` radius); the self-collision sphere ``pairs`` (P, 2) grouped by
    link pair (``pair_r2``, ``lpair_ptr``, ``lpairs`` (K, 2), ``lpair_r2``); ``flat``: a planar task."""

    chain: ChainArrays
    thresh: np.ndarray
    link_ptr: np.ndarray
    link_sph: np.ndarray
    link_frame: np.ndarray
    link_mid: np.ndarray
    link_r: np.ndarray
    cull: bool
    obs_c: np.ndarray
    obs_r: np.ndarray
    box_r: np.ndarray
    box_crot: np.ndarray
    box_h: np.ndarray
    corner: float
    pairs: np.ndarray
    pair_r2: np.ndarray
    lpair_ptr: np.ndarray
    lpairs: np.ndarray
    lpair_r2: np.ndarray
    flat: bool


def constants(inp: SphereInputs) -> tuple:
    """The kernels' argument tuple (``c`` of :func:`valid_states`, :func:`edge_valid`): the arrays of ``inp`` in the
    order of :func:`_state_ok`, and its scratch arrays."""
    ch = inp.chain
    f64 = lambda x: np.ascontiguousarray(x, dtype=np.float64)  # noqa: E731
    i64 = lambda x: np.ascontiguousarray(x, dtype=np.int64)  # noqa: E731
    dof, S, L = len(ch.revolute), len(inp.thresh), len(inp.link_frame)
    return (
        np.ascontiguousarray(ch.revolute, dtype=np.bool_),
        f64(ch.rot_terms),
        f64(ch.axis_off),
        f64(ch.off_r),
        f64(ch.axes),
        i64(ch.point_frame),
        f64(ch.point_local),
        f64(inp.thresh),
        i64(inp.link_ptr),
        i64(inp.link_sph),
        i64(inp.link_frame),
        f64(inp.link_mid),
        f64(inp.link_r),
        bool(inp.cull),
        f64(inp.obs_c),
        f64(inp.obs_r),
        f64(inp.box_r),
        f64(inp.box_crot),
        f64(inp.box_h),
        float(inp.corner),
        i64(inp.pairs),
        f64(inp.pair_r2),
        i64(inp.lpair_ptr),
        i64(inp.lpairs),
        f64(inp.lpair_r2),
        bool(inp.flat),
        np.zeros((dof + 1, 3, 4)),
        np.zeros((S, 3)),
        np.zeros((L, 3)),
        np.zeros(S, dtype=np.bool_),
        np.zeros(3),
        np.zeros(len(inp.obs_r) + inp.box_h.shape[1]),
    )


def _parity(dtype):
    """``run()``: the validity of 400 random Panda configurations in EnvSpheres3D with its extra objects (clearance
    1 cm) and of 40 edges between them (float64 whatever ``dtype``)."""
    import torch

    from mpd.data.checkers import SphereChecker
    from mpd.tasks import load_task

    task = load_task("EnvSpheres3D-RobotPanda")
    checker = SphereChecker(task, extra_objects=True, clearance=0.01)
    q = task.robot.random_q(400, torch.Generator().manual_seed(35)).numpy()

    def run() -> dict:
        edges = [checker.edge_valid(q[k], q[k + 1], 24) for k in range(0, 80, 2)]
        return {"valid": checker.valid(q), "edges": np.array(edges)}

    return run, {"rtol": 0.0, "atol": 0.0}


kernels.register(
    kernels.Kernel("sphere", __name__, "mpd.data.checkers.SphereChecker.check (numpy)", _parity, ("float64",))
)
