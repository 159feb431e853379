"""An environment: fixed obstacles plus optional extra objects, optionally rotated about the robot base's z axis."""

from __future__ import annotations

import numpy as np
import torch

from mpd.envs.grid import AuthorsGridSDF, GridSDF
from mpd.envs.primitives import ObjectSet, Primitive, build_primitives


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
        self._authors_grids: dict[str, AuthorsGridSDF] = {}

    def __repr__(self) -> str:
        n_extra = len(self.extra) if self.extra is not None else 0
        n_fixed = len(self.fixed)
        return f"Environment({self.dim}-D, {n_fixed} obstacles, {n_extra} extra, rotation {self.rotation_deg} deg)"

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
        if which not in self._grids:
            objs = self.fixed if which == "fixed" else self.extra
            self._grids[which] = GridSDF(objs, *self.workspace, self.spec.sdf_cell_size)
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
            elif mode == "authors":  # the authors' lookup (a measurement only; values, no gradient)
                if grad:
                    raise ValueError("the authors' grid lookup is for validity measurements only (no gradient)")
                if name not in self._authors_grids:
                    self._authors_grids[name] = AuthorsGridSDF(objs, *self.workspace, self.spec.sdf_cell_size)
                d, g = self._authors_grids[name].query(x), None
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
