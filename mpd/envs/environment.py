"""An environment: fixed obstacles plus optional extra objects, optionally rotated about the robot base's z axis, plus
any obstacles given at plan time (:meth:`Environment.with_obstacles`)."""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Sequence

import numpy as np
import torch

from mpd.envs.grid import AuthorsGridSDF, GridSDF
from mpd.envs.primitives import ObjectSet, Primitive, build_primitives

# The extra objects' grid of a scene with obstacles given at plan time is a truncated SDF (GridSDF's ``truncate``):
# exact below this distance, this distance beyond it. The collision cost reads it only below a sphere's radius plus
# the cost margin (at most 0.06 + 0.07 m for the Panda), the validity checks below the radius plus the validity
# margin, so both are unchanged by it (tests/test_mbm_prior.py).
PLAN_TIME_GRID_TRUNCATION = 0.3


class Environment:
    """Signed distance of a task's scene.

    ``sdf(x, mode)`` is the minimum over the fixed obstacles and (if enabled) the extra objects. ``mode`` is
    ``analytic`` (exact, used by the evaluator) or ``nearest`` / ``trilinear`` (a precomputed grid per object set,
    as in the paper, used by the planner's costs). Grids are built on first use.
    """

    def __init__(self, spec, extra_objects: bool = False, rotation_deg: float = 0.0):
        self.spec = spec
        self.dim = spec.dim
        self.extra_objects = bool(extra_objects)
        self.rotation_deg = float(rotation_deg)
        self.workspace = (np.asarray(spec.workspace[0], float), np.asarray(spec.workspace[1], float))
        self.fixed = ObjectSet(
            self.dim, build_primitives(spec.obstacles, self.dim, rotation_deg), spec.box_corner_radius
        )
        self.extra = (
            ObjectSet(self.dim, build_primitives(spec.extra_objects, self.dim, rotation_deg), spec.box_corner_radius)
            if extra_objects and spec.extra_objects
            else None
        )
        self._grids: dict[str, GridSDF] = {}
        self._authors_grids: dict[tuple[str, bool], AuthorsGridSDF] = {}  # (set, with gradients)
        # obstacles given at plan time (world frame, not rotated with the scene): part of the "extra" set
        self.obstacles: tuple[Primitive, ...] = ()
        self._base: Environment | None = None

    def __repr__(self) -> str:
        n_extra = len(self.extra) if self.extra is not None else 0
        n_fixed = len(self.fixed)
        more = f", {len(self.obstacles)} given at plan time" if self.obstacles else ""
        return (
            f"Environment({self.dim}-D, {n_fixed} obstacles, {n_extra} extra{more}, rotation {self.rotation_deg} deg)"
        )

    @property
    def key(self) -> tuple:
        """What makes this scene: (extra objects on, rotation, digest of the plan-time obstacles or "")."""
        return (self.extra_objects, self.rotation_deg, obstacles_digest(self.obstacles) if self.obstacles else "")

    def with_obstacles(self, primitives: Sequence[Primitive]) -> Environment:
        """This scene with more obstacles (world-frame primitives, e.g. what a robot's perception reports).

        They join the extra objects' set (whose grid and checker rule they share; boxes get the task's corner radius),
        so every consumer of the scene (the collision cost's grid, the ground-truth checker, the planners that check
        states) sees them. The fixed obstacles and their grid are shared with this environment, not rebuilt: a new
        obstacle set costs one grid of the extra set."""
        prims = tuple(primitives)
        for p in prims:
            if p.centre.shape != (self.dim,):
                raise ValueError(
                    f"obstacle {p.name or p.kind}: centre has {p.centre.shape[0]} coordinates, not {self.dim}"
                )
        if not prims:
            return self
        env = copy.copy(self)
        base = list(self.extra.primitives) if self.extra is not None else []
        env.extra = ObjectSet(self.dim, base + list(prims), self.spec.box_corner_radius)
        env.obstacles = self.obstacles + prims
        env._base = self._base or self  # the fixed objects' grid is read from (and built in) the base scene
        env._grids = {k: v for k, v in self._grids.items() if k == "fixed"}
        env._authors_grids = {k: v for k, v in self._authors_grids.items() if k[0] == "fixed"}
        return env

    @property
    def primitives(self) -> list[tuple[Primitive, bool]]:
        """(primitive, is_extra) for drawing and for building the PyBullet scene."""
        out = [(p, False) for p in self.fixed.primitives]
        if self.extra is not None:
            out += [(p, True) for p in self.extra.primitives]
        return out

    def _sets(self):
        return [s for s in (self.fixed, self.extra) if s is not None and len(s)]

    def grid(self, which: str = "fixed") -> GridSDF:
        if which == "fixed" and which not in self._grids and self._base is not None:
            self._grids[which] = self._base.grid("fixed")
        if which not in self._grids:
            objs = self.fixed if which == "fixed" else self.extra
            # a plan-time scene's grid is built for each new set of obstacles: truncated (exact below the distance,
            # built around the objects only; 45 s -> ~1 s for a MotionBenchMaker shelf on a 3 x 3 x 2.5 m workspace)
            tau = PLAN_TIME_GRID_TRUNCATION if which == "extra" and self.obstacles else None
            self._grids[which] = GridSDF(objs, *self.workspace, self.spec.sdf_cell_size, truncate=tau)
        return self._grids[which]

    def sdf(self, x: torch.Tensor, grad: bool = False, mode: str = "analytic"):
        """Signed distance (...) of points x (..., dim), and its gradient (..., dim) with ``grad``."""
        best_d, best_g = None, None
        for name, objs in (("fixed", self.fixed), ("extra", self.extra)):
            if objs is None or not len(objs):
                continue
            if mode == "analytic":
                r = objs.sdf(x, grad=grad)
                d, g = r if grad else (r, None)
            elif mode == "authors":  # the authors' lookup (a measurement: their validity verdicts, their cost)
                key = (name, bool(grad))
                if key not in self._authors_grids:
                    self._authors_grids[key] = AuthorsGridSDF(objs, *self.workspace, self.spec.sdf_cell_size, grad)
                grid = self._authors_grids[key]
                d, g = grid.query_grad(x) if grad else (grid.query(x), None)
            else:
                d, g = self.grid(name).query(x, mode)
            if best_d is None:
                best_d, best_g = d, g
            else:
                closer = d < best_d
                best_d = torch.where(closer, d, best_d)
                if grad:
                    best_g = torch.where(closer[..., None], g, best_g)
        if best_d is None:
            best_d = torch.full(x.shape[:-1], float("inf"), dtype=x.dtype, device=x.device)
            best_g = torch.zeros_like(x)
        return (best_d, best_g) if grad else best_d


def obstacles_digest(prims: Sequence[Primitive]) -> str:
    """A content hash of obstacles (kinds, centres, sizes, rotations to float64 bits), order-sensitive."""
    h = hashlib.sha256()
    for p in prims:
        h.update(p.kind.encode())
        for a in (p.centre, np.float64(p.radius), p.half_size, p.rotation):
            if a is not None:
                h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]
