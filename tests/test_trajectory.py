"""Trajectory parametrizations: B-spline bases against scipy, boundary conditions, the chain rule against
autograd, waypoint interpolation and differences, fitting, and properties (hypothesis)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import BSpline

from mpd.tasks import load_task
from mpd.trajectory import (
    BSplineTrajectory,
    WaypointTrajectory,
    bspline_basis,
    clamped_uniform_knots,
    make_parametrization,
)
from mpd.trajectory.waypoints import gradient_matrix, interpolation_matrix

F64 = torch.float64
SIZES = [(7, 3), (8, 2), (10, 5), (12, 4), (16, 1), (22, 5), (29, 5), (37, 5)]


def _scipy_basis(n: int, p: int, s: np.ndarray, d: int) -> np.ndarray:
    spl = BSpline(clamped_uniform_knots(n, p), np.eye(n), p)
    return (spl.derivative(d) if d else spl)(s)


@pytest.mark.parametrize("n, p, d", [(n, p, d) for n, p in SIZES for d in range(min(p, 2) + 1)])
def test_basis_vs_scipy(n, p, d):
    s = np.concatenate([np.linspace(0, 1, 128), np.random.default_rng(0).uniform(0, 1, 200)])
    np.testing.assert_allclose(
        bspline_basis(clamped_uniform_knots(n, p), p, s, d),
        _scipy_basis(n, p, s, d),
        rtol=0,
        atol=1e-9 * max(1, n**d),
    )


@pytest.mark.parametrize("n, p", SIZES)
def test_knots(n, p):
    t = clamped_uniform_knots(n, p)
    assert len(t) == n + p + 1
    assert np.all(t[: p + 1] == 0) and np.all(t[-p - 1 :] == 1)
    np.testing.assert_allclose(np.diff(t[p:-p]), 1 / (n - p))


def _context(dof: int, B: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, dof, generator=g, dtype=F64), torch.randn(B, dof, generator=g, dtype=F64), g)


PARAMS = [
    ("bspline", False, lambda: BSplineTrajectory(22, 5, 128, 10.0, ee_goal=False)),
    ("bspline", True, lambda: BSplineTrajectory(29, 5, 128, 10.0, ee_goal=True)),
    ("bspline-cubic", False, lambda: BSplineTrajectory(9, 3, 64, 5.0, ee_goal=False)),
    ("waypoints", False, lambda: WaypointTrajectory(22, 128, 10.0, ee_goal=False)),
    ("waypoints", True, lambda: WaypointTrajectory(16, 100, 4.0, ee_goal=True)),
]
IDS = [f"{k}-{'ee' if ee else 'joint'}" for k, ee, _ in PARAMS]


@pytest.mark.parametrize("kind, ee, make", PARAMS, ids=IDS)
def test_boundary_conditions(kind, ee, make):
    par = make()
    qs, qg, g = _context(7, 5, 0)
    free = torch.randn(5, par.n_free, 7, generator=g, dtype=F64)
    d = par.dense(free, qs, None if ee else qg)
    assert d.q.shape == d.dq_ds.shape == d.ddq_ds2.shape == (5, par.n_points, 7)
    torch.testing.assert_close(d.q[:, 0], qs, rtol=0, atol=1e-12)
    end = free[:, -1] if ee else qg  # with an end-effector goal the final configuration is the last free row
    torch.testing.assert_close(d.q[:, -1], end, rtol=0, atol=1e-12)
    if kind.startswith("bspline"):
        for x in (d.dq_ds, d.ddq_ds2):
            torch.testing.assert_close(x[:, [0, -1]], torch.zeros(5, 2, 7, dtype=F64), rtol=0, atol=1e-9)
    torch.testing.assert_close(d.dq_dt, d.dq_ds / par.duration)
    torch.testing.assert_close(d.ddq_dt2, d.ddq_ds2 / par.duration**2)


@pytest.mark.parametrize("kind, ee, make", PARAMS, ids=IDS)
def test_full_and_free_rows_round_trip(kind, ee, make):
    par = make()
    qs, qg, g = _context(3, 4, 1)
    free = torch.randn(4, par.n_free, 3, generator=g, dtype=F64)
    w = par.full(free, qs, None if ee else qg)
    assert w.shape == (4, par.n_params, 3)
    torch.testing.assert_close(par.free_rows(w), free, rtol=0, atol=0)
    # the dense trajectory is the basis applied to the full parameter matrix
    B = torch.as_tensor(par.basis)
    torch.testing.assert_close(par.dense(free, qs, None if ee else qg).q, B @ w, rtol=0, atol=1e-12)


@pytest.mark.parametrize("kind, ee, make", PARAMS, ids=IDS)
def test_grad_to_free_vs_autograd(kind, ee, make):
    par = make()
    qs, qg, g = _context(4, 3, 2)
    free = torch.randn(3, par.n_free, 4, generator=g, dtype=F64, requires_grad=True)
    G = [torch.randn(3, par.n_points, 4, generator=g, dtype=F64) for _ in range(3)]
    d = par.dense(free, qs, None if ee else qg)
    cost = (G[0] * d.q).sum() + (G[1] * d.dq_ds).sum() + (G[2] * d.ddq_ds2).sum()
    (auto,) = torch.autograd.grad(cost, free)
    torch.testing.assert_close(par.grad_to_free(*G), auto, rtol=1e-12, atol=1e-10)
    # any of the three may be left out
    (auto_q,) = torch.autograd.grad((G[0] * par.dense(free, qs, None if ee else qg).q).sum(), free)
    torch.testing.assert_close(par.grad_to_free(G[0]), auto_q, rtol=1e-12, atol=1e-10)
    (auto_dd,) = torch.autograd.grad((G[2] * par.dense(free, qs, None if ee else qg).ddq_ds2).sum(), free)
    torch.testing.assert_close(par.grad_to_free(None, None, G[2]), auto_dd, rtol=1e-12, atol=1e-10)


def test_float32_and_shapes():
    par = BSplineTrajectory(22, 5, 128, 10.0)
    qs, qg, g = _context(2, 8, 3)
    free = torch.randn(8, par.n_free, 2, generator=g, dtype=F64)
    d64 = par.dense(free, qs, qg)
    d32 = par.dense(free.float(), qs.float(), qg.float())
    assert d32.q.dtype == torch.float32
    torch.testing.assert_close(d32.q.double(), d64.q, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="free parameters of shape"):
        par.dense(free[:, :-1], qs, qg)
    with pytest.raises(ValueError, match="q_goal"):
        par.dense(free, qs, None)
    with pytest.raises(ValueError, match="at least"):
        BSplineTrajectory(6, 5)


def test_task_parametrizations():
    for name, n_free in [
        ("EnvSimple2D-RobotPointMass2D", 16),
        ("EnvWarehouse-RobotPanda", 24),
        ("EnvPlanar2Link-RobotPlanar2Link", 16),
    ]:
        t = load_task(name)
        par = make_parametrization(t)
        assert par.n_free == n_free and par.ee_goal == t.ee_goal and par.duration == t.spec.trajectory.duration
        wp = make_parametrization(t, "waypoints")
        assert wp.n_params == t.spec.trajectory.n_control_points
    with pytest.raises(ValueError, match="unknown parametrization"):
        make_parametrization(t, "chebyshev")


# ------------------------------------------------------------------------------------------- waypoints
@pytest.mark.parametrize("n_points, n_w", [(128, 22), (100, 16), (64, 3), (50, 50)])
def test_waypoint_interpolation_vs_numpy(n_points, n_w):
    A = interpolation_matrix(n_points, n_w)
    w = np.random.default_rng(0).normal(size=(n_w, 3))
    s = np.linspace(0, 1, n_points)
    want = np.stack([np.interp(s, np.linspace(0, 1, n_w), w[:, k]) for k in range(3)], 1)
    np.testing.assert_allclose(A @ w, want, rtol=0, atol=1e-12)
    D = gradient_matrix(n_points, 1 / (n_points - 1))
    np.testing.assert_allclose(D @ want, np.gradient(want, s, axis=0, edge_order=1), rtol=0, atol=1e-9)


def test_waypoint_derivatives_are_finite_differences():
    par = WaypointTrajectory(16, 128, 10.0)
    qs, qg, g = _context(2, 2, 4)
    d = par.dense(torch.randn(2, par.n_free, 2, generator=g, dtype=F64), qs, qg)
    s = np.linspace(0, 1, 128)
    np.testing.assert_allclose(d.dq_ds.numpy(), np.gradient(d.q.numpy(), s, axis=1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(d.ddq_ds2.numpy(), np.gradient(d.dq_ds.numpy(), s, axis=1), rtol=0, atol=1e-7)


# --------------------------------------------------------------------------------------------- fitting
def _smooth_paths(n: int = 128) -> np.ndarray:
    s = np.linspace(0, 1, n)[:, None]
    a = np.concatenate([0.8 * np.sin(np.pi * s) + s, np.cos(1.5 * np.pi * s), 0.5 * s**2 - s], 1)  # (n, 3)
    b = np.concatenate([np.sin(2 * np.pi * s) * 0.4, -s, 0.3 * np.cos(np.pi * s)], 1)
    return np.stack([a, b])


def _hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    d = torch.cdist(torch.as_tensor(a), torch.as_tensor(b))
    return max(d.min(0).values.max().item(), d.min(1).values.max().item())


def test_fit_of_a_path_with_crowded_states():
    """A real EnvSpheres3D path (context 12138 of the -cpu dataset: one edge of 4 rad, seven of 0.3-0.7 rad),
    resampled the ``v1`` way (about equal states per edge): its states crowd into the short edges, the chord-length
    parameter leaves a knot interval without data and FITPACK fails (this stopped a dataset generation). The fit
    falls back to equally spaced parameters and still follows the path; resampled by arc length (the default now),
    the paper's fit works on it as is."""
    import dataclasses

    from scipy import interpolate

    from mpd.data.definition import load_definition
    from mpd.data.generate import _tools
    from mpd.data.planning import JointSpacePlanner, problem_seed
    from mpd.trajectory.bspline import _chord_parameter

    rd = load_definition("EnvSpheres3D-RobotPanda-cpu")
    checker, sampler, planner, par = _tools(rd)[:4]
    c = sampler.sample(np.random.default_rng([rd.definition.seed, 12138]))
    seed = problem_seed(rd.definition.seed, 12138)
    v1 = JointSpacePlanner(checker, dataclasses.replace(planner.settings, resample="v1"), planner.n_points)
    for p, fails in [
        (v1.plan(c.q_start, c.q_goal, seed).path, True),
        (planner.plan(c.q_start, c.q_goal, seed).path, False),
    ]:
        u = _chord_parameter(p)
        try:
            interpolate.splprep(list(p.T), u=u, k=par.degree, t=par.knots, task=-1, s=0)
            failed = False
        except TypeError:
            failed = True
        assert failed == fails
        w = par.fit(p[None])[0]
        assert np.isfinite(w).all()
        np.testing.assert_allclose(w[[0, -1]], p[[0, -1]], atol=1e-12)
        # within 3 % of its length (2.2 % and 0.5 % measured): most of it is the pinned end rows (zero velocity and
        # acceleration at both ends) on the long first edge; the dataset's ground-truth check judges the fit
        length = np.linalg.norm(np.diff(p, axis=0), axis=1).sum()
        assert _hausdorff(p, par.basis @ w) < 0.03 * length


@pytest.mark.parametrize(
    "make",
    [
        lambda: BSplineTrajectory(22, 5, 128),
        lambda: BSplineTrajectory(29, 5, 128),
        lambda: WaypointTrajectory(22, 128),
    ],
    ids=["bspline22", "bspline29", "waypoints"],
)
def test_fit_follows_a_smooth_path(make):
    par = make()
    paths = _smooth_paths()
    w = par.fit(paths)
    assert w.shape == (2, par.n_params, 3)
    np.testing.assert_allclose(w[:, 0], paths[:, 0], atol=1e-12)
    np.testing.assert_allclose(w[:, -1], paths[:, -1], atol=1e-12)
    dense = par.basis @ w  # (2, n_points, 3)
    for path, q in zip(paths, dense):
        length = np.linalg.norm(np.diff(path, axis=0), axis=1).sum()
        assert _hausdorff(path, q) < 0.01 * length
    # the fitted rows are the free rows plus the context: full(free_rows(W)) == W
    free = torch.as_tensor(par.free_rows(w))
    torch.testing.assert_close(
        par.full(free, torch.as_tensor(paths[:, 0]), torch.as_tensor(paths[:, -1])),
        torch.as_tensor(w),
        rtol=0,
        atol=1e-12,
    )


# ------------------------------------------------------------------------------------------ properties
@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 5).flatmap(lambda p: st.tuples(st.just(p), st.integers(max(p + 1, 2), 30))),
    st.lists(st.floats(0, 1), min_size=1, max_size=20),
)
def test_basis_partition_of_unity(pn, s):
    p, n = pn
    s = np.asarray(s)
    knots = clamped_uniform_knots(n, p)
    N = bspline_basis(knots, p, s, 0)
    np.testing.assert_allclose(N.sum(1), 1.0, atol=1e-12)
    assert np.all(N >= -1e-15)
    for d in range(1, min(p, 2) + 1):  # derivatives of a partition of unity sum to zero
        np.testing.assert_allclose(bspline_basis(knots, p, s, d).sum(1), 0.0, atol=1e-8 * n**d)


@settings(max_examples=25, deadline=None)
@given(
    st.sampled_from([(BSplineTrajectory, 22, 5), (BSplineTrajectory, 9, 3), (WaypointTrajectory, 12, None)]),
    st.booleans(),
    st.integers(0, 2**31 - 1),
)
def test_straight_line_is_reproduced(cfg, ee, seed):
    """Rows on the segment q_s -> q_g at param_phases() give a path along that segment, monotone from start
    to goal; for waypoints it is the segment at constant speed (the B-spline's fixed boundary rows slow its
    ends)."""
    cls, n, p = cfg
    par = cls(n, p, 64, 3.0, ee_goal=ee) if p else cls(n, 64, 3.0, ee_goal=ee)
    qs, qg, _ = _context(3, 1, seed % 1000)
    line = qs[:, None] + torch.as_tensor(par.param_phases())[None, :, None] * (qg - qs)[:, None]
    free = par.free_rows(line)
    d = par.dense(free, qs, None if ee else qg)
    delta = (qg - qs)[:, None]
    lam = ((d.q - qs[:, None]) * delta).sum(-1, keepdim=True) / (delta * delta).sum(-1, keepdim=True)
    torch.testing.assert_close(d.q, qs[:, None] + lam * delta, rtol=0, atol=1e-10)
    # the end: q_goal, or with an end-effector goal the last free row (a point of the segment)
    end = 1.0 if not ee else (((free[0, -1] - qs[0]) * delta[0, 0]).sum() / (delta[0, 0] ** 2).sum()).item()
    assert lam[0, 0].abs() < 1e-12 and (lam[0, -1] - end).abs() < 1e-12
    assert torch.all(torch.diff(lam[0, :, 0]) >= -1e-12)
    if cls is WaypointTrajectory:
        torch.testing.assert_close(lam[0, :, 0], torch.as_tensor(par.phase), rtol=0, atol=1e-10)


@settings(max_examples=25, deadline=None)
@given(st.floats(-3, 3), st.floats(-3, 3), st.integers(0, 1000))
def test_dense_is_affine_in_the_free_rows(a, b, seed):
    par = BSplineTrajectory(12, 5, 32)
    qs, qg, g = _context(2, 1, seed)
    f1, f2 = (torch.randn(1, par.n_free, 2, generator=g, dtype=F64) for _ in range(2))
    z = par.dense(torch.zeros_like(f1), qs, qg).q
    lhs = par.dense(a * f1 + b * f2, qs, qg).q - z
    rhs = a * (par.dense(f1, qs, qg).q - z) + b * (par.dense(f2, qs, qg).q - z)
    torch.testing.assert_close(lhs, rhs, rtol=0, atol=1e-10)
