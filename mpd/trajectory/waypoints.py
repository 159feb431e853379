"""Waypoint trajectories (the paper's ablation): n_w waypoints, linear interpolation, finite differences."""

from __future__ import annotations

import numpy as np

from mpd.trajectory.base import LinearTrajectory


def interpolation_matrix(n_points: int, n_waypoints: int) -> np.ndarray:
    """(n_points, n_waypoints) piecewise-linear interpolation of waypoints placed at equidistant phases."""
    s = np.linspace(0.0, 1.0, n_points) * (n_waypoints - 1)
    k = np.minimum(np.floor(s).astype(int), n_waypoints - 2)
    w = s - k
    A = np.zeros((n_points, n_waypoints))
    A[np.arange(n_points), k] = 1 - w
    A[np.arange(n_points), k + 1] += w
    return A


def gradient_matrix(n: int, ds: float) -> np.ndarray:
    """Central differences inside, one-sided at the ends (numpy.gradient with edge_order=1), as a matrix."""
    D = np.zeros((n, n))
    i = np.arange(1, n - 1)
    D[i, i - 1], D[i, i + 1] = -0.5 / ds, 0.5 / ds
    D[0, 0], D[0, 1] = -1 / ds, 1 / ds
    D[-1, -2], D[-1, -1] = -1 / ds, 1 / ds
    return D


class WaypointTrajectory(LinearTrajectory):
    """n_w waypoints at equidistant phases; the first is q_start, the last q_goal (free with an end-effector goal).

    Velocities and accelerations come from finite differences of the dense path, so they are piecewise constant
    between waypoints and jump at them: what the paper's B-spline-vs-waypoints ablation measures.
    """

    name = "waypoints"

    def __init__(self, n_waypoints: int, n_points: int = 128, duration: float = 10.0, ee_goal: bool = False):
        super().__init__(n_waypoints, n_points, duration, ee_goal)
        if n_waypoints < 3:
            raise ValueError("a waypoint trajectory needs at least 3 waypoints")
        self.basis = interpolation_matrix(n_points, n_waypoints)
        D = gradient_matrix(n_points, 1.0 / (n_points - 1))
        self.basis_d1 = D @ self.basis
        self.basis_d2 = D @ self.basis_d1
        n_free = n_waypoints - 1 if ee_goal else n_waypoints - 2
        self.a_free = np.zeros((n_waypoints, n_free))
        self.a_free[1 : 1 + n_free, :] = np.eye(n_free)
        self.a_start = np.zeros(n_waypoints)
        self.a_start[0] = 1.0
        self.a_goal = np.zeros(n_waypoints)
        if not ee_goal:
            self.a_goal[-1] = 1.0

    def param_phases(self) -> np.ndarray:
        return np.linspace(0.0, 1.0, self.n_params)

    def fit(self, paths: np.ndarray) -> np.ndarray:
        """Waypoints = the dense path read at the waypoint phases (linear interpolation along the path index)."""
        paths = np.asarray(paths, dtype=np.float64)
        n = paths.shape[1]
        s = np.linspace(0.0, n - 1, self.n_params)
        k = np.minimum(np.floor(s).astype(int), n - 2)
        w = (s - k)[None, :, None]
        return (1 - w) * paths[:, k] + w * paths[:, k + 1]
