"""Shaded 3-D meshes of spheres and boxes for mplot3d, and the one depth-sorted collection they share."""

from __future__ import annotations

import weakref

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import to_rgba
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

# All polygons of one 3-D axes live in a single Poly3DCollection: mplot3d depth-sorts the faces within a
# collection, but orders separate collections only as wholes, which puts a robot in front of a shelf it is
# behind.
_POLYS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_LIGHT = np.array([-0.35, -0.55, 0.76]) / np.linalg.norm([-0.35, -0.55, 0.76])


def shade(color, normals: np.ndarray, alpha: float = 1.0) -> np.ndarray:
    """Lambert shading with some ambient light: (F, 4) RGBA face colours."""
    rgb = np.array(to_rgba(color)[:3])
    k = 0.55 + 0.45 * np.clip(normals @ _LIGHT, 0.0, 1.0)
    out = np.empty((len(normals), 4))
    out[:, :3] = np.clip(rgb[None] * k[:, None], 0, 1)
    out[:, 3] = alpha
    return out


def add_polys(ax: Axes, verts: np.ndarray, colors: np.ndarray) -> None:
    """Add faces (F, k, 3) with RGBA colours (F, 4) to the axes' one scene collection (rebuilt each call)."""
    store = _POLYS.setdefault(ax, {"verts": [], "colors": [], "artist": None})
    store["verts"].append(verts)
    store["colors"].append(colors)
    if store["artist"] is not None:
        store["artist"].remove()
    v = np.concatenate(store["verts"])
    c = np.concatenate(store["colors"])
    # edges in the face colour close the hairline seams that antialiasing leaves between adjacent quads
    coll = Poly3DCollection(v, facecolors=c, edgecolors=c, linewidths=0.25, zorder=1)
    store["artist"] = ax.add_collection3d(coll)


def sphere_mesh(centre, radius: float, n_u: int = 20, n_v: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Quads (n_u n_v, 4, 3) of a UV sphere and their outward normals (n_u n_v, 3)."""
    u = np.linspace(0, 2 * np.pi, n_u + 1)
    v = np.linspace(0, np.pi, n_v + 1)
    d = np.stack(
        np.broadcast_arrays(
            np.cos(u)[:, None] * np.sin(v)[None], np.sin(u)[:, None] * np.sin(v)[None], np.cos(v)[None]
        ),
        -1,
    )  # (n_u+1, n_v+1, 3) unit directions
    quads = np.stack([d[:-1, :-1], d[1:, :-1], d[1:, 1:], d[:-1, 1:]], 2).reshape(-1, 4, 3)
    normals = quads.mean(1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return np.asarray(centre)[None, None] + radius * quads, normals


_BOX_FACES = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
_BOX_NORMALS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=float)


def box_mesh(centre, half_size, rotation) -> tuple[np.ndarray, np.ndarray]:
    """The six faces (6, 4, 3) of a rotated box (rotation: box frame to world) and their normals (6, 3)."""
    bits = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=float)
    corners = np.asarray(centre) + (bits * 2 - 1) * np.asarray(half_size) @ np.asarray(rotation).T
    return corners[_BOX_FACES], _BOX_NORMALS @ np.asarray(rotation).T
