"""Clamped uniform B-splines (the paper's trajectory parametrization, section IV-E)."""

from __future__ import annotations

import warnings

import numpy as np
from scipy import interpolate

from mpd.trajectory.base import LinearTrajectory


def clamped_uniform_knots(n_control: int, degree: int) -> np.ndarray:
    """[0]*(p+1), n_b - p - 1 equidistant inner knots, [1]*(p+1): the paper's eq. (knots), |u| = n_b + p + 1."""
    inner = np.arange(1, n_control - degree) / (n_control - degree)
    return np.concatenate([np.zeros(degree + 1), inner, np.ones(degree + 1)])


def bspline_basis(knots: np.ndarray, degree: int, s: np.ndarray, derivative: int = 0) -> np.ndarray:
    """Basis functions (or their derivatives) at phases s by the Cox-de Boor recursion: (len(s), n_control).

    The right end s = 1 belongs to the last non-empty knot interval, so that the clamped spline interpolates its
    last control point there.
    """
    t = np.asarray(knots, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    n_control = len(t) - degree - 1
    # degree-0 indicators on half-open intervals; the last non-empty interval is closed on the right
    last = np.max(np.nonzero(t[:-1] < t[1:])[0])
    n0 = len(t) - 1
    N = ((t[None, :-1] <= s[:, None]) & (s[:, None] < t[None, 1:])).astype(np.float64)
    N[s >= t[last + 1], :] = 0.0
    N[s >= t[last + 1], last] = 1.0
    # derivative d of order p: differentiate the recursion (d of the lower-degree basis at each level)
    return _recurse(t, N, s, degree, derivative, n0)[:, :n_control]


def _recurse(t, N0, s, p, d, n0):
    if p == 0:
        return N0 if d == 0 else np.zeros_like(N0)
    low = _recurse(t, N0, s, p - 1, d - 1 if d > 0 else 0, n0)
    n = n0 - p  # number of degree-p functions
    a = t[p : p + n] - t[:n]
    b = t[p + 1 : p + 1 + n] - t[1 : 1 + n]
    inv_a = np.divide(1.0, a, out=np.zeros_like(a), where=a > 0)
    inv_b = np.divide(1.0, b, out=np.zeros_like(b), where=b > 0)
    if d == 0:
        return (s[:, None] - t[None, :n]) * inv_a * low[:, :n] + (
            t[None, p + 1 : p + 1 + n] - s[:, None]
        ) * inv_b * low[:, 1 : 1 + n]
    # N^(d)_{i,p} = p (N^(d-1)_{i,p-1} / a_i - N^(d-1)_{i+1,p-1} / b_i)
    return p * (inv_a * low[:, :n] - inv_b * low[:, 1 : 1 + n])


class BSplineTrajectory(LinearTrajectory):
    """Degree-p clamped B-spline with n_b control points.

    Rows 0-2 are q_start and the last three q_goal (zero velocity and acceleration at both ends). With an
    end-effector goal the final configuration is free: the last free row is repeated three times (the authors'
    structure [q_start x3, inner x (L-1), w_last x3]), so the network models n_b - 5 rows instead of n_b - 6.
    """

    name = "bspline"

    def __init__(
        self,
        n_control: int,
        degree: int = 5,
        n_points: int = 128,
        duration: float = 10.0,
        ee_goal: bool = False,
    ):
        super().__init__(n_control, n_points, duration, ee_goal)
        if n_control < max(degree + 1, 7):
            raise ValueError(
                f"a degree-{degree} B-spline with fixed boundary rows needs at least {max(degree + 1, 7)} control"
                " points"
            )
        self.degree = int(degree)
        self.knots = clamped_uniform_knots(n_control, degree)
        self.basis = bspline_basis(self.knots, degree, self.phase, 0)
        self.basis_d1 = bspline_basis(self.knots, degree, self.phase, 1)
        self.basis_d2 = bspline_basis(self.knots, degree, self.phase, 2)
        n_free = n_control - 5 if ee_goal else n_control - 6
        self.a_free = np.zeros((n_control, n_free))
        if ee_goal:
            self.a_free[3 : n_control - 3, : n_free - 1] = np.eye(n_free - 1)
            self.a_free[n_control - 3 :, n_free - 1] = 1.0
        else:
            self.a_free[3 : n_control - 3, :] = np.eye(n_free)
        self.a_start = np.zeros(n_control)
        self.a_start[:3] = 1.0
        self.a_goal = np.zeros(n_control)
        if not ee_goal:
            self.a_goal[-3:] = 1.0

    def settings(self) -> dict:
        return {**super().settings(), "degree": self.degree}

    def param_phases(self) -> np.ndarray:
        # Greville abscissae: a B-spline reproduces linear functions when control point i sits at xi_i
        p = self.degree
        return np.array([self.knots[i + 1 : i + p + 1].mean() for i in range(self.n_params)])

    def free_rows(self, w):
        # rows 3 .. n-4 (and the final configuration, once, with an end-effector goal)
        n = self.n_params
        return w[..., 3 : n - 2, :] if self.ee_goal else w[..., 3 : n - 3, :]

    def fit(self, paths: np.ndarray) -> np.ndarray:
        """Least-squares B-spline through each dense path (scipy ``splprep`` with this knot vector and the chord-length
        parameter, the paper's choice), then the boundary rows are set to the path's end points.
        (N, n, dof) -> (N, n_control, dof).

        When the chord-length parameter leaves a knot interval without data (a path whose simplification kept many
        short edges crowds its states into part of its length, and FITPACK then fails: the least-squares problem is
        singular), the path is fitted with its states equally spaced in the parameter instead; a path that fails both
        gets NaN control points (judged out of range, so not used for training)."""
        paths = np.asarray(paths, dtype=np.float64)
        out = np.empty((paths.shape[0], self.n_params, paths.shape[2]))
        for i, path in enumerate(paths):
            w = self._fit_one(path, _chord_parameter(path))
            if w is None:
                w = self._fit_one(path, np.linspace(0.0, 1.0, len(path)))
            if w is None:
                out[i] = np.nan
                continue
            w[:3] = path[0]
            w[-3:] = path[-1]
            out[i] = w
        return out

    def _fit_one(self, path: np.ndarray, u: np.ndarray) -> np.ndarray | None:
        inner = self.knots[self.degree + 1 : -self.degree - 1]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # splprep warns on nearly straight 2-D paths; the fit is still fine
            try:
                (t, c, _k), _u = interpolate.splprep(list(path.T), u=u, k=self.degree, t=self.knots, task=-1, s=0)
            except (TypeError, ValueError):  # FITPACK's error codes (scipy raises TypeError for some of them)
                return None
        assert np.allclose(t[self.degree + 1 : -self.degree - 1], inner)
        return np.stack(c, 1)[: self.n_params]


def _chord_parameter(path: np.ndarray) -> np.ndarray:
    """Normalised cumulative chord length (splprep's own default), kept strictly increasing for repeated points."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    seg = np.maximum(seg, 1e-9 * max(seg.sum(), 1e-12) + 1e-15)
    u = np.concatenate([[0.0], np.cumsum(seg)])
    return u / u[-1]
