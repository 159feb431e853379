"""Analytic signed distance (and gradient) of spheres and rotated, rounded boxes in 2-D and 3-D, batched."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch


def quat_wxyz_to_matrix(q: Sequence[float]) -> np.ndarray:
    w, x, y, z = (float(v) for v in q)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot_z(deg: float, dim: int) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return r[:dim, :dim]


@dataclass(frozen=True)
class Primitive:
    """One obstacle in world coordinates; ``rotation`` maps box-frame vectors to the world."""

    kind: str  # "sphere" | "box"
    centre: np.ndarray
    radius: float = 0.0
    half_size: np.ndarray | None = None
    rotation: np.ndarray | None = None
    name: str = ""


class ObjectSet:
    """A set of spheres and boxes; ``sdf`` is the minimum over them (the scene's signed distance)."""

    def __init__(self, dim: int, primitives: Sequence[Primitive], corner_radius: float = 0.0):
        self.dim = dim
        self.primitives = list(primitives)
        self.corner_radius = float(corner_radius)
        sph = [p for p in self.primitives if p.kind == "sphere"]
        box = [p for p in self.primitives if p.kind == "box"]
        self._sc = np.array([p.centre for p in sph], dtype=np.float64).reshape(-1, dim)
        self._sr = np.array([p.radius for p in sph], dtype=np.float64)
        self._bc = np.array([p.centre for p in box], dtype=np.float64).reshape(-1, dim)
        self._bh = np.array([p.half_size for p in box], dtype=np.float64).reshape(-1, dim)
        self._br = np.array([p.rotation for p in box], dtype=np.float64).reshape(-1, dim, dim)
        self._cache: dict[tuple, tuple[torch.Tensor, ...]] = {}

    def __len__(self) -> int:
        return len(self.primitives)

    def _t(self, dtype, device):
        key = (dtype, str(device))
        if key not in self._cache:
            self._cache[key] = tuple(
                torch.as_tensor(a, dtype=dtype, device=device)
                for a in (self._sc, self._sr, self._bc, self._bh, self._br)
            )
        return self._cache[key]

    def sdf(self, x: torch.Tensor, grad: bool = False, chunk: int = 1 << 16):
        """Signed distance of points x (..., dim); with ``grad`` also its gradient (..., dim)."""
        shape = x.shape[:-1]
        flat = x.reshape(-1, self.dim)
        if len(self) == 0:
            d = torch.full(shape, float("inf"), dtype=x.dtype, device=x.device)
            return (d, torch.zeros_like(x)) if grad else d
        outs, grads = [], []
        for start in range(0, flat.shape[0], chunk):
            d, g = self._sdf_chunk(flat[start : start + chunk], grad)
            outs.append(d)
            grads.append(g)
        d = torch.cat(outs).reshape(shape)
        if not grad:
            return d
        return d, torch.cat(grads).reshape(*shape, self.dim)

    def _sdf_chunk(self, x: torch.Tensor, grad: bool):
        sc, sr, bc, bh, br = self._t(x.dtype, x.device)
        ds, gs = [], []
        if len(sr):
            diff = x[:, None, :] - sc[None]  # (N, n, D)
            nrm = diff.norm(dim=-1)
            ds.append(nrm - sr)
            if grad:
                gs.append(diff / nrm.clamp_min(1e-12)[..., None])
        if len(bh):
            r = self.corner_radius
            local = torch.einsum("nmd,mde->nme", x[:, None, :] - bc[None], br)  # R^T (x - c)
            q = local.abs() - bh + r
            qpos = q.clamp_min(0)
            out = qpos.norm(dim=-1)
            qmax, kmax = q.max(-1)
            ds.append(out + qmax.clamp_max(0) - r)
            if grad:
                sgn = torch.where(local >= 0, 1.0, -1.0).to(x.dtype)
                g_out = sgn * qpos / out.clamp_min(1e-12)[..., None]
                g_in = sgn * torch.nn.functional.one_hot(kmax, self.dim).to(x.dtype)
                g_local = torch.where((out > 0)[..., None], g_out, g_in)
                gs.append(torch.einsum("mde,nme->nmd", br, g_local))
        d = torch.cat(ds, 1)
        dmin, imin = d.min(1)
        if not grad:
            return dmin, None
        g = torch.cat(gs, 1)
        return dmin, g.gather(1, imin[:, None, None].expand(-1, 1, self.dim))[:, 0]


def build_primitives(specs, dim: int, rotation_deg: float = 0.0) -> list[Primitive]:
    """Turn task-file object specs into world-frame primitives, rotated about the base z axis by ``rotation_deg``."""
    rz = rot_z(rotation_deg, dim)
    prims = []
    for o in specs:
        c = rz @ np.asarray(o.centre, dtype=np.float64)
        if o.type == "sphere":
            prims.append(Primitive("sphere", c, radius=float(o.radius), name=o.name))
        else:
            r = quat_wxyz_to_matrix(o.orientation_wxyz) if o.orientation_wxyz is not None else np.eye(3)
            r = rz @ r[:dim, :dim]
            prims.append(
                Primitive("box", c, half_size=np.asarray(o.size, dtype=np.float64) / 2, rotation=r, name=o.name)
            )
    return prims
