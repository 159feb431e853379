"""mpd: Motion Planning Diffusion (Carvalho et al., IEEE T-RO 2025), reproducible.

The Python API (:mod:`mpd.api`): ``mpd.load_planner(task, method)`` and ``planner.plan(q_start, goal, obstacles=...)``
with ``mpd.Sphere``, ``mpd.Box`` and ``mpd.Pose``; imported on first use, so that ``import mpd`` stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_API = ("Box", "MotionPlan", "MotionPlanner", "PlanningInputError", "Pose", "Sphere", "load_planner")


def __getattr__(name: str) -> Any:
    if name in _API:
        return getattr(importlib.import_module("mpd.api"), name)
    raise AttributeError(f"module 'mpd' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_API])


__all__ = [*_API, "__version__"]
