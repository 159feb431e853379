"""Compiled validity of configurations under the sphere model: the fast path of :class:`SphereChecker`.

The planner asks about one state or one short edge at a time. In numpy each such call is mostly
per-operation overhead for the Panda (7 joints x a few small array operations, two SDF passes); this module
does the same computation per state in one compiled loop (numba, ``cache=True``) and stops at the first
colliding state, so an edge in collision usually costs a few states. The arithmetic is the numpy checker's:
forward kinematics by the chain's Rodrigues terms, per-link bounding spheres for culling, the analytic SDF of
spheres and rounded boxes, self-collision sphere pairs behind link-pair culling. Only the summation order of a
few dot products differs, so a state exactly on the clearance boundary (to ~1e-15) may be judged differently;
``tests/test_data.py`` pins the two implementations to each other on states all over each task's scene.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


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


def constants(checker) -> tuple:
    """The arrays the kernels take, from a built :class:`SphereChecker` (contiguous float64 / int64 / bool; the
    scene in 3-D: a planar task's obstacles at z = 0, its boxes unbounded along z)."""
    ch = checker.robot.chain
    dim = checker._dim
    f64 = lambda x: np.ascontiguousarray(x, dtype=np.float64)  # noqa: E731
    i64 = lambda x: np.ascontiguousarray(x, dtype=np.int64)  # noqa: E731
    L = len(checker._links)
    S = len(checker._radii)
    links_frame, links_mid = [], []
    for k in range(L):
        col = checker._wb[:, k]
        f = int(np.flatnonzero(col)[-1]) // 4  # the homogeneous 1 marks the link's frame
        links_frame.append(f)
        links_mid.append(col[4 * f : 4 * f + 3])
    obs_c = np.zeros((3, len(checker._sr)))
    obs_c[:dim] = checker._sc_t
    bc, br, bh = checker._boxes  # (Nb, dim), (Nb, dim, dim), (Nb, dim)
    nb = len(bh)
    box_r = np.zeros((nb, 3, 3))
    box_r[:, :dim, :dim] = br
    box_c = np.zeros((nb, 3))
    box_c[:, :dim] = bc
    box_h = np.full((nb, 3), 1e300)
    box_h[:, :dim] = bh
    if dim == 2:
        box_r[:, 2, 2] = 1.0
    box_crot = np.einsum("na,nak->kn", box_c, box_r)
    # self-collision pairs grouped by their link pair
    pairs = checker._pairs.reshape(-1, 2)
    order = np.argsort(checker._pair_group, kind="stable") if len(pairs) else np.zeros(0, np.int64)
    K = len(checker._lpairs)
    lpair_ptr = np.searchsorted(checker._pair_group[order], np.arange(K + 1)) if len(pairs) else np.zeros(K + 1)
    return (
        np.ascontiguousarray(checker._revolute, dtype=np.bool_),
        f64(checker._rot_terms),
        f64(checker._axis_off),
        f64(checker._off_r),
        f64(checker._axes),
        i64(ch.point_joint + 1),
        f64(ch._point_local),
        f64(checker._thresh),
        i64(np.searchsorted(np.sort(checker._group), np.arange(L + 1))),
        i64(np.argsort(checker._group, kind="stable")),
        i64(links_frame),
        f64(np.array(links_mid).reshape(L, 3)),
        f64(checker._rb + checker.clearance),
        bool(checker._cull),
        f64(obs_c),
        f64(checker._sr),
        f64(box_r.transpose(1, 2, 0)),
        f64(box_crot),
        f64(box_h.T),
        float(checker._corner),
        i64(pairs[order]),
        f64(checker._pair_r2[order]),
        i64(lpair_ptr),
        i64(checker._lpairs),
        f64(checker._lpair_r**2),
        dim == 2,
        np.zeros((checker.dof + 1, 3, 4)),
        np.zeros((S, 3)),
        np.zeros((L, 3)),
        np.zeros(S, dtype=np.bool_),
        np.zeros(3),
        np.zeros(len(checker._sr) + nb),
    )
