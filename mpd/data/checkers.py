"""Validity checkers for sampling contexts and for the planner: the sphere model in numpy, or PyBullet meshes.

The planner asks about one configuration or one short edge at a time, where torch's per-call overhead (see
``mpd data measure``) dominates. :class:`SphereChecker` is the sphere model of
:class:`mpd.collision.CollisionChecker` (same FK, same analytic SDF of spheres and rounded boxes, same
self-collision pairs): ``check`` in numpy, pinned to ``CollisionChecker`` by a test, and ``valid`` /
``edge_valid``, the same computation compiled per state (:mod:`mpd.data.sphere_kernel`, numba), pinned to
``check`` by a test; the compiled path is what the planner, the context sampler and the stored-path check use
(for the Panda ~20x less time per edge than numpy's per-call overhead allowed).
:class:`MeshChecker` asks PyBullet about the URDF collision geometry (the authors' data-generation checker).

Both answer ``valid(Q)`` for configurations Q (M, dof) with the clearance they were built with: the robot is
in collision when a sphere (mesh) comes closer to an obstacle than ``clearance``; self collision is checked
without margin (the task's ``collision.self_collision`` switches it for the sphere model).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from mpd import kernels
from mpd.tasks import Task

CheckerKind = Literal["spheres", "meshes"]
_EYE3 = np.eye(3)


class SphereChecker:
    """The sphere model of a task scene in numpy (float64), for batches of a few to a few hundred states.

    Spheres are culled per link: a link whose bounding sphere keeps more than its radius plus the clearance
    from every obstacle (or from the other link of a self-collision pair) cannot have a colliding sphere,
    because the SDF is 1-Lipschitz; only the spheres of the remaining links are evaluated.
    """

    kind = "spheres"

    def __init__(
        self, task: Task, extra_objects: bool = False, clearance: float = 0.0, rotation_deg: float = 0.0, env=None
    ):
        """``env``: the scene itself (e.g. one with obstacles given at plan time) instead of ``extra_objects`` and
        ``rotation_deg``."""
        self.task = task
        self.robot = robot = task.robot
        self.dof = robot.dof
        self.clearance = float(clearance)
        # chain constants (the arrays the torch FK folds the fixed joints into)
        self._chain = ch = robot.chain.kernel_inputs()
        self._rot_terms = ch.rot_terms  # (dof, 3, 9)
        self._axis_off = ch.axis_off  # (dof, 3, 2)
        self._off_r = ch.off_r
        self._axes = ch.axes
        self._revolute = ch.revolute
        self._w = ch.wpoints  # (4 (dof + 1), S): stacked frames [R | p] -> sphere centres
        self._radii = robot.sphere_radii.numpy()
        self._dim = robot.task_dim
        self._thresh = self._radii + self.clearance  # every sphere needs sdf(c) - r > clearance
        self._linear = None
        if not self._revolute.any():
            # only prismatic joints (the point mass): the centres are an affine function of q
            basis = np.vstack([np.zeros(self.dof), np.eye(self.dof)])
            c = (self._frames(basis) @ self._w).transpose(0, 2, 1)[..., : self._dim]
            self._linear = (c[0], (c[1:] - c[0]).reshape(self.dof, -1))
        self._init_links()
        pairs = robot.self_pairs.numpy() if task.spec.collision.self_collision else np.zeros((0, 2), int)
        self._init_pairs(pairs)
        self._init_obstacles(task.env(extra_objects, rotation_deg) if env is None else env)
        self._kernel = None

    def _init_links(self) -> None:
        names = self.robot.sphere_links
        self._links = list(dict.fromkeys(names))
        self._group = np.array([self._links.index(n) for n in names])  # link of each sphere
        frame = self._chain.point_frame  # frame of each sphere (0 = root)
        wb, rb = [], []
        for k in range(len(self._links)):
            sel = self._group == k
            f = int(frame[sel][0])  # a link's spheres share its frame
            local = self._w[4 * f : 4 * f + 3, sel].T  # (n, 3) sphere centres in that frame
            mid = (local.min(0) + local.max(0)) / 2
            rb.append(float((np.linalg.norm(local - mid, axis=1) + self._radii[sel]).max()))
            col = np.zeros(self._w.shape[0])
            col[4 * f : 4 * f + 3] = mid
            col[4 * f + 3] = 1.0
            wb.append(col)
        self._wb = np.stack(wb, 1)  # (4 (dof + 1), L)
        self._rb = np.array(rb)
        # culling pays off only when links carry several spheres
        self._cull = len(self._radii) >= 2 * len(self._links)

    def _init_pairs(self, pairs: np.ndarray) -> None:
        self._pairs = pairs
        self._pair_r2 = (self._radii[pairs[:, 0]] + self._radii[pairs[:, 1]]) ** 2 if len(pairs) else np.zeros(0)
        lp = sorted({(int(self._group[i]), int(self._group[j])) for i, j in pairs})
        self._lpairs = np.array(lp, dtype=np.int64).reshape(-1, 2)
        self._pair_group = np.array(
            [lp.index((int(self._group[i]), int(self._group[j]))) for i, j in pairs], dtype=np.int64
        )
        self._lpair_r = self._rb[self._lpairs[:, 0]] + self._rb[self._lpairs[:, 1]] if len(lp) else np.zeros(0)

    def _init_obstacles(self, env) -> None:
        prims = [p for p, _extra in env.primitives]
        sph = [p for p in prims if p.kind == "sphere"]
        box = [p for p in prims if p.kind == "box"]
        d = self._dim
        sc = np.array([p.centre for p in sph], dtype=np.float64).reshape(-1, d)
        self._sr = np.array([p.radius for p in sph], dtype=np.float64)
        self._sc_t = sc.T.copy()
        self._sc2 = (sc**2).sum(-1)
        bc = np.array([p.centre for p in box], dtype=np.float64).reshape(-1, d)
        bh = np.array([p.half_size for p in box], dtype=np.float64).reshape(-1, d)
        br = np.array([p.rotation for p in box], dtype=np.float64).reshape(-1, d, d)
        self._nb = nb = len(bh)
        self._corner = float(env.spec.box_corner_radius)
        # All box frames as one matrix product, R_n^T (x - c_n) = x^T R_n - c_n^T R_n, with the coordinate
        # axis before the box axis (numpy reduces slowly over a last axis of length 2-3): column k * nb + n.
        self._rcat = br.transpose(1, 2, 0).reshape(d, d * nb)
        self._crot = np.einsum("nd,nde->en", bc, br).reshape(-1)
        self._bh_r = (bh - self._corner).T.reshape(-1)  # rounded box: q = |local| - (h - r)
        self._boxes = (bc, br, bh - self._corner)  # the same boxes for the compiled kernel

    def settings(self) -> dict:
        return {"kind": self.kind, "clearance": self.clearance, "self_collision": bool(len(self._pairs))}

    # ------------------------------------------------------------------ kinematics and distances
    def _frames(self, q: np.ndarray) -> np.ndarray:
        """All frames as [R | p] blocks of one (M, 3, 4 (dof + 1)) array (the torch chain's layout)."""
        M = q.shape[0]
        T = np.zeros((M, 3, self.dof + 1, 4))
        T[:, :, 0, :3] = _EYE3
        R = _EYE3
        p = np.zeros((M, 3))
        s, co = np.sin(q), 1.0 - np.cos(q)
        for j in range(self.dof):
            o = p + R @ self._axis_off[j][:, 1]
            if self._revolute[j]:
                t = R @ self._rot_terms[j]  # (M, 3, 9): [R Off | R Off K | R Off K^2], Rodrigues
                R = t[..., 0:3] + s[:, j, None, None] * t[..., 3:6] + co[:, j, None, None] * t[..., 6:9]
                p = o
            else:
                R = R @ self._off_r[j]
                p = o + (R @ self._axes[j]) * q[:, j, None]
            T[:, :, j + 1, :3] = R
            T[:, :, j + 1, 3] = p
        return T.reshape(M, 3, -1)

    def centres(self, q: np.ndarray) -> np.ndarray:
        """Sphere centres (M, S, task_dim) of configurations q (M, dof)."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, self.dof)
        if self._linear is not None:
            c0, cq = self._linear
            return c0 + (q @ cq).reshape(len(q), -1, self._dim)
        return (self._frames(q) @ self._w).transpose(0, 2, 1)[..., : self._dim]

    def sdf(self, x: np.ndarray) -> np.ndarray:
        """Signed distance of points x (..., dim) to the scene (+inf without obstacles)."""
        shape = x.shape[:-1]
        x = x.reshape(-1, self._dim)
        out = np.full(x.shape[0], np.inf)
        if len(self._sr):
            x2 = sum(x[:, k] ** 2 for k in range(self._dim))
            d2 = x2[:, None] - 2.0 * (x @ self._sc_t) + self._sc2
            out = np.minimum(out, (np.sqrt(np.maximum(d2, 0.0)) - self._sr).min(-1))
        if self._nb:
            qd = (np.abs(x @ self._rcat - self._crot) - self._bh_r).reshape(-1, self._dim, self._nb)
            pos = np.maximum(qd, 0.0)
            outside = np.sqrt(sum(pos[:, k] ** 2 for k in range(self._dim)))
            inside = np.minimum(qd.max(1), 0.0)
            out = np.minimum(out, (outside + inside - self._corner).min(-1))
        return out.reshape(shape)

    # ------------------------------------------------------------------ validity
    def check(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Environment-free and self-free flags (M,) of configurations q (M, dof)."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, self.dof)
        if self._cull:
            T = self._frames(q)
            c = (T @ self._w).transpose(0, 2, 1)[..., : self._dim]  # (M, S, dim)
        else:
            c = self.centres(q)
        if self._cull:
            b = (T @ self._wb).transpose(0, 2, 1)[..., : self._dim]  # link bounding spheres (M, L, dim)
            near = (self.sdf(b) <= self._rb + self.clearance)[:, self._group]  # (M, S)
            ok = np.ones(near.shape, dtype=bool)
            m, s = np.nonzero(near)
            ok[m, s] = self.sdf(c[m, s]) > self._thresh[s]
            env = ok.all(-1)
        else:
            env = (self.sdf(c) > self._thresh).all(-1)
        slf = np.ones(len(q), dtype=bool)
        if len(self._pairs):
            if self._cull:
                la, lb = self._lpairs[:, 0], self._lpairs[:, 1]
                dl = b[:, la] - b[:, lb]
                lnear = sum(dl[..., k] ** 2 for k in range(self._dim)) < self._lpair_r**2  # (M, K)
                m, i = np.nonzero(lnear[:, self._pair_group])
            else:
                m, i = np.nonzero(np.ones((len(q), len(self._pairs)), dtype=bool))
            if len(m):
                diff = c[m, self._pairs[i, 0]] - c[m, self._pairs[i, 1]]
                hit = sum(diff[:, k] ** 2 for k in range(self._dim)) < self._pair_r2[i]
                slf[m[hit]] = False
        return env, slf

    def valid(self, q: np.ndarray) -> np.ndarray:
        """Validity flags (M,) of configurations q (M, dof): the compiled kernel (``sphere`` of :mod:`mpd.kernels`;
        ``check`` in numpy is its reference, what the ``torch`` mode runs)."""
        from mpd.data import sphere_kernel

        q = np.ascontiguousarray(q, dtype=np.float64).reshape(-1, self.dof)
        if not kernels.active("sphere"):
            env, slf = self.check(q)
            return env & slf
        out = np.empty(len(q), dtype=bool)
        sphere_kernel.valid_states(q, self.kernel_constants(), out, False)
        return out

    def edge_valid(self, a: np.ndarray, b: np.ndarray, n: int, chunk: int = 32) -> bool:
        """Whether the n states ``edge_states`` checks on the edge a -> b are all valid: the end state, then every
        ``ceil(n / chunk)``-th state, then the rest, stopping at the first invalid one (in the ``torch`` mode of
        :mod:`mpd.kernels`: all n states by ``check``)."""
        from mpd.data import sphere_kernel

        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        if not kernels.active("sphere"):
            if n <= 0:
                return True
            env, slf = self.check(a + np.arange(1, int(n) + 1)[:, None] / int(n) * (b - a))
            return bool((env & slf).all())
        return bool(sphere_kernel.edge_valid(a, b, int(n), int(chunk), self.kernel_constants()))

    def kernel_inputs(self):
        """The arrays of :mod:`mpd.data.sphere_kernel` for this checker (a
        :class:`mpd.data.sphere_kernel.SphereInputs`; the scene in 3-D)."""
        from mpd.data import sphere_kernel

        dim = self._dim
        L, nb = len(self._links), self._nb
        links_frame, links_mid = [], []
        for k in range(L):
            col = self._wb[:, k]
            f = int(np.flatnonzero(col)[-1]) // 4  # the homogeneous 1 marks the link's frame
            links_frame.append(f)
            links_mid.append(col[4 * f : 4 * f + 3])
        obs_c = np.zeros((3, len(self._sr)))
        obs_c[:dim] = self._sc_t
        bc, br, bh = self._boxes  # (Nb, dim), (Nb, dim, dim), (Nb, dim)
        box_r = np.zeros((nb, 3, 3))
        box_r[:, :dim, :dim] = br
        box_c = np.zeros((nb, 3))
        box_c[:, :dim] = bc
        box_h = np.full((nb, 3), 1e300)
        box_h[:, :dim] = bh
        if dim == 2:
            box_r[:, 2, 2] = 1.0
        # self-collision pairs grouped by their link pair
        pairs = self._pairs.reshape(-1, 2)
        order = np.argsort(self._pair_group, kind="stable") if len(pairs) else np.zeros(0, np.int64)
        K = len(self._lpairs)
        lpair_ptr = np.searchsorted(self._pair_group[order], np.arange(K + 1)) if len(pairs) else np.zeros(K + 1)
        return sphere_kernel.SphereInputs(
            chain=self._chain,
            thresh=self._thresh,
            link_ptr=np.searchsorted(np.sort(self._group), np.arange(L + 1)),
            link_sph=np.argsort(self._group, kind="stable"),
            link_frame=np.array(links_frame),
            link_mid=np.array(links_mid).reshape(L, 3),
            link_r=self._rb + self.clearance,
            cull=bool(self._cull),
            obs_c=obs_c,
            obs_r=self._sr,
            box_r=box_r.transpose(1, 2, 0),
            box_crot=np.einsum("na,nak->kn", box_c, box_r),
            box_h=box_h.T,
            corner=float(self._corner),
            pairs=pairs[order],
            pair_r2=self._pair_r2[order],
            lpair_ptr=lpair_ptr,
            lpairs=self._lpairs,
            lpair_r2=self._lpair_r**2,
            flat=dim == 2,
        )

    def kernel_constants(self) -> tuple:
        """The argument tuple of :mod:`mpd.data.sphere_kernel` for this checker (built once)."""
        if self._kernel is None:
            from mpd.data import sphere_kernel

            self._kernel = sphere_kernel.constants(self.kernel_inputs())
        return self._kernel

    def close(self) -> None:
        pass


class MeshChecker:
    """PyBullet URDF collision geometry with a clearance (see :mod:`mpd.envs.pybullet_scene`)."""

    kind = "meshes"

    def __init__(
        self,
        task: Task,
        extra_objects: bool = False,
        clearance: float = 0.0,
        rotation_deg: float = 0.0,
        self_pairs: str = "sphere_pairs",
    ):
        from mpd.envs.pybullet_scene import PyBulletScene

        self.task = task
        self.dof = task.robot.dof
        self.clearance = float(clearance)
        # a task without self collision in its sphere model gets none here either (like with like)
        self.self_pairs = self_pairs if task.spec.collision.self_collision else "none"
        self.scene = PyBulletScene(
            task.robot, task.env(extra_objects, rotation_deg), clearance=clearance, self_pairs=self.self_pairs
        )

    def settings(self) -> dict:
        return {"kind": self.kind, "clearance": self.clearance, "self_pairs": self.self_pairs}

    def check(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.scene.check(q)

    def valid(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64).reshape(-1, self.dof)
        out = np.empty(len(q), dtype=bool)
        sc = self.scene
        for i, qi in enumerate(q):  # stop at the first hit per state: env first (cheaper, more often hit)
            sc.set_q(qi)
            out[i] = sc.env_free() and sc.self_free()
        return out

    def close(self) -> None:
        self.scene.close()


def make_checker(
    task: Task,
    kind: CheckerKind,
    clearance: float,
    extra_objects: bool = False,
    self_pairs: str = "sphere_pairs",
) -> SphereChecker | MeshChecker:
    if kind == "spheres":
        return SphereChecker(task, extra_objects, clearance)
    if kind == "meshes":
        return MeshChecker(task, extra_objects, clearance, self_pairs=self_pairs)
    raise ValueError(f"unknown validity checker {kind!r} (spheres, meshes)")


def grid_count(length: float, step: float) -> int:
    """Steps an edge of this length is checked in: ceil(length / step), at least 1. (The tolerance keeps an
    edge made of k whole steps at k steps despite rounding: resampled paths rely on it.)"""
    return max(1, math.ceil(length / step - 1e-9))


def edge_states(a: np.ndarray, b: np.ndarray, step: float) -> np.ndarray:
    """The states an edge a -> b is checked at: ``grid_count`` equal steps, b included, a excluded (a is known
    valid), like OMPL's discrete motion validator."""
    d = b - a
    n = grid_count(math.sqrt(float(d @ d)), step)
    t = np.arange(1, n + 1, dtype=np.float64)[:, None] / n
    return a + t * (b - a)


def path_states(path: np.ndarray, step: float) -> np.ndarray:
    """Every state a path is checked at: its first state and each edge's :func:`edge_states`."""
    path = np.asarray(path, dtype=np.float64)
    return np.concatenate([path[:1]] + [edge_states(path[i], path[i + 1], step) for i in range(len(path) - 1)])


def path_valid(checker: SphereChecker | MeshChecker, path: np.ndarray, step: float) -> bool:
    """Whether a polyline is valid at the checker's resolution ``step`` (a joint-space distance)."""
    return bool(checker.valid(path_states(path, step)).all())
