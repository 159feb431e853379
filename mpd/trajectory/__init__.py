"""B-spline and waypoint parametrizations (linear maps from parameters to dense q, q', q''), fitting paths."""

from __future__ import annotations

from mpd.trajectory.base import Dense, LinearTrajectory
from mpd.trajectory.bspline import BSplineTrajectory, bspline_basis, clamped_uniform_knots
from mpd.trajectory.waypoints import WaypointTrajectory

PARAMETRIZATIONS = ("bspline", "waypoints")


def make_parametrization(task, kind: str = "bspline") -> LinearTrajectory:
    """The trajectory parametrization of a task (``bspline`` or ``waypoints``) with the task's settings."""
    tr = task.spec.trajectory
    if kind == "bspline":
        return BSplineTrajectory(tr.n_control_points, tr.bspline_degree, tr.n_points, tr.duration, task.ee_goal)
    if kind == "waypoints":
        return WaypointTrajectory(tr.n_waypoints or tr.n_control_points, tr.n_points, tr.duration, task.ee_goal)
    raise ValueError(f"unknown parametrization {kind!r} (known: {', '.join(PARAMETRIZATIONS)})")


__all__ = [
    "PARAMETRIZATIONS",
    "BSplineTrajectory",
    "Dense",
    "LinearTrajectory",
    "WaypointTrajectory",
    "bspline_basis",
    "clamped_uniform_knots",
    "make_parametrization",
]
