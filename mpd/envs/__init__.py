"""Obstacle primitives, analytic and grid signed-distance fields, environment transforms, the PyBullet scene."""

from mpd.envs.environment import Environment
from mpd.envs.grid import GridSDF
from mpd.envs.primitives import ObjectSet, Primitive, build_primitives, quat_wxyz_to_matrix, rot_z

__all__ = [
    "Environment",
    "GridSDF",
    "ObjectSet",
    "Primitive",
    "build_primitives",
    "quat_wxyz_to_matrix",
    "rot_z",
]
