"""Environments: analytic SDF against independent computations, its gradient, the grid SDF, and the collision
fractions of the six tasks against the reference table."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import TASKS

from mpd.collision import collision_fractions
from mpd.envs import GridSDF, ObjectSet, Primitive, quat_wxyz_to_matrix, rot_z
from mpd.envs.primitives import build_primitives
from mpd.tasks import load_task
from mpd.tasks.spec import ObjectSpec

F64 = torch.float64


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _box_surface(c, h, R, spacing: float) -> np.ndarray:
    """Points on the surface of a box (centre c, half sizes h, rotation R), at most ``spacing`` apart."""
    dim = len(c)
    out = []
    for axis in range(dim):
        others = [k for k in range(dim) if k != axis]
        grids = np.meshgrid(
            *[np.linspace(-h[k], h[k], int(np.ceil(2 * h[k] / spacing)) + 1) for k in others], indexing="ij"
        )
        face = np.zeros((grids[0].size, dim))
        for k, g in zip(others, grids):
            face[:, k] = g.ravel()
        for sign in (-1, 1):
            f = face.copy()
            f[:, axis] = sign * h[axis]
            out.append(f)
    return np.asarray(c) + np.concatenate(out) @ np.asarray(R).T


def _sphere_surface(c, r, n: int) -> np.ndarray:
    if len(c) == 2:
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.asarray(c) + r * np.stack([np.cos(a), np.sin(a)], 1)
    i = np.arange(n) + 0.5  # Fibonacci sphere: near-uniform points
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    return np.asarray(c) + r * np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


def _min_dist(x: np.ndarray, surface: np.ndarray) -> np.ndarray:
    xt, st = torch.as_tensor(x), torch.as_tensor(surface)
    return torch.cdist(xt, st).min(1).values.numpy()


def _inside_box(x, c, h, R) -> np.ndarray:
    local = (np.asarray(x) - c) @ np.asarray(R)
    return (np.abs(local) <= h).all(1)


QUAT = tuple(np.array([0.9, 0.2, -0.3, 0.25]) / np.linalg.norm([0.9, 0.2, -0.3, 0.25]))
ROT3 = quat_wxyz_to_matrix(QUAT)  # a rotation about no coordinate axis


@pytest.mark.parametrize(
    "dim, R",
    [(2, np.eye(2)), (2, rot_z(37.0, 2)), (3, np.eye(3)), (3, ROT3)],
    ids=["2d", "2d-rotated", "3d", "3d-rotated"],
)
def test_box_sdf_vs_surface_samples(dim, R):
    c, h = np.array([0.1, -0.2, 0.3])[:dim], np.array([0.15, 0.08, 0.12])[:dim]
    spacing = 0.002 if dim == 2 else 0.006
    surface = _box_surface(c, h, R, spacing)
    x = c + _rng(1).uniform(-0.4, 0.4, (1500, dim))
    d = ObjectSet(dim, [Primitive("box", c, half_size=h, rotation=R)]).sdf(torch.as_tensor(x)).numpy()
    inside = _inside_box(x, c, h, R)
    assert 0.01 < inside.mean() < 0.5
    np.testing.assert_array_equal(d <= 0, inside)
    # the nearest surface sample is at most half a (diagonal) grid step further than the true surface
    ref = _min_dist(x, surface)
    assert np.all(np.abs(d) <= ref + 1e-12) and np.all(ref - np.abs(d) <= spacing * np.sqrt(dim - 1) / 2 + 1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_sphere_sdf_vs_surface_samples(dim):
    c, r = np.array([0.3, -0.1, 0.2])[:dim], 0.17
    n = 4000 if dim == 2 else 60_000
    surface = _sphere_surface(c, r, n)
    x = c + _rng(2).uniform(-0.4, 0.4, (1500, dim))
    d = ObjectSet(dim, [Primitive("sphere", c, radius=r)]).sdf(torch.as_tensor(x)).numpy()
    np.testing.assert_array_equal(d <= 0, np.linalg.norm(x - c, axis=1) <= r)
    ref = _min_dist(x, surface)
    assert np.abs(np.abs(d) - ref).max() < (0.002 if dim == 2 else 0.004)


@pytest.mark.parametrize("dim", [2, 3])
def test_rounded_box_is_the_inner_box_dilated(dim):
    """A box with corner radius r: the set within r of the box shrunk by r (a Minkowski sum)."""
    c, h, r = np.zeros(dim), np.array([0.2, 0.1, 0.15])[:dim], 0.03
    R = rot_z(20.0, dim) if dim == 2 else ROT3
    spacing = 0.002 if dim == 2 else 0.005
    inner = _box_surface(c, h - r, R, spacing)
    x = c + _rng(3).uniform(-0.35, 0.35, (1500, dim))
    x = x[~_inside_box(x, c, h - r, R)]  # outside the inner box, distance to it = distance to its surface
    d = ObjectSet(dim, [Primitive("box", c, half_size=h, rotation=R)], corner_radius=r).sdf(torch.as_tensor(x)).numpy()
    ref = _min_dist(x, inner) - r
    assert np.abs(d - ref).max() <= spacing * np.sqrt(dim - 1) / 2 + 1e-12


def _scene(dim: int) -> ObjectSet:
    """Two spheres, a box rotated about no axis (3-D), an axis-aligned box; all turned 25 deg about z."""
    specs = [
        ObjectSpec("sphere", [0.3, 0.2, 0.1][:dim], radius=0.15),
        ObjectSpec("sphere", [-0.4, 0.1, -0.2][:dim], radius=0.1),
        ObjectSpec(
            "box",
            [0.0, -0.35, 0.05][:dim],
            size=[0.5, 0.2, 0.3][:dim],
            orientation_wxyz=QUAT if dim == 3 else None,
        ),
        ObjectSpec("box", [-0.1, 0.45, 0.0][:dim], size=[0.3, 0.1, 0.2][:dim]),
    ]
    return ObjectSet(dim, build_primitives(specs, dim, rotation_deg=25.0), corner_radius=0.01)


@pytest.mark.parametrize("dim", [2, 3])
def test_sdf_gradient_vs_autograd_and_finite_differences(dim):
    objs = _scene(dim)
    x = torch.as_tensor(_rng(4).uniform(-0.7, 0.7, (3000, dim)))
    d, g = objs.sdf(x, grad=True)
    xa = x.clone().requires_grad_(True)
    (auto,) = torch.autograd.grad(objs.sdf(xa).sum(), xa)
    torch.testing.assert_close(g, auto, rtol=0, atol=1e-12)
    torch.testing.assert_close(g.norm(dim=-1), torch.ones(len(x), dtype=F64), rtol=0, atol=1e-12)
    h = 1e-6
    fd = torch.stack([(objs.sdf(x + h * e) - objs.sdf(x - h * e)) / (2 * h) for e in torch.eye(dim, dtype=F64)], -1)
    # the SDF has kinks (medial axes); a random point lies within h of one with probability ~1e-5
    close = ((fd - g).abs() < 1e-6).all(-1)
    assert close.float().mean() > 0.999


# -------------------------------------------------------------------------------------------- grid SDF
def _grid_points(objs: ObjectSet, lo, hi, cell: float, n: int, seed: int):
    """Random points at least one cell from every surface and where the gradient is locally constant (away
    from the medial axes, where the nearest grid node may lie on the other side of a kink)."""
    x = torch.as_tensor(lo + _rng(seed).uniform(0, 1, (n, len(lo))) * (np.asarray(hi) - lo))
    d, g = objs.sdf(x, grad=True)
    smooth = torch.ones(len(x), dtype=torch.bool)
    for e in torch.cat([torch.eye(len(lo)), -torch.eye(len(lo))]).to(F64):
        smooth &= (objs.sdf(x + cell * e, grad=True)[1] * g).sum(-1) > 0.999
    return x, d, g, d.abs() >= cell, smooth


@pytest.mark.parametrize("mode", ["nearest", "trilinear"])
@pytest.mark.parametrize("name", ["EnvSimple2D-RobotPointMass2D", "EnvNarrowPassageDense2D-RobotPointMass2D"])
def test_grid_sdf_vs_analytic_2d(name, mode):
    env = load_task(name).env(extra_objects=True)
    for which, objs in (("fixed", env.fixed), ("extra", env.extra)):
        grid = env.grid(which)
        x, d, g, away, smooth = _grid_points(objs, *env.workspace, grid.cell, 20_000, 5)
        gd, gg = grid.query(x.float(), mode)
        err = (gd.double() - d).abs()
        assert err[away].max() <= grid.cell
        cos = torch.nn.functional.cosine_similarity(gg.double(), g, dim=-1)
        assert cos[away & smooth].min() > 0.95
        assert (away & smooth).float().mean() > 0.7  # the filter keeps most points


@pytest.fixture(scope="module")
def warehouse_grids():
    """Warehouse obstacles (the rotated table included) on a grid over the robot's side of the scene, with the
    test points; built once for both lookup modes. The full workspace grid (1.6 M nodes) is what the benchmark
    and the checker's grid test build."""
    env = load_task("EnvWarehouse-RobotPanda").env(extra_objects=True)
    lo, hi = np.array([-0.2, -0.8, -0.3]), np.array([1.0, 0.8, 0.9])
    out = []
    for objs in (env.fixed, env.extra):
        grid = GridSDF(objs, lo, hi, 0.02)
        out.append((objs, grid, _grid_points(objs, lo, hi, grid.cell, 20_000, 6)))
    return out


@pytest.mark.parametrize("mode", ["nearest", "trilinear"])
def test_grid_sdf_vs_analytic_3d(warehouse_grids, mode):
    for _, grid, (x, d, g, away, smooth) in warehouse_grids:
        gd, gg = grid.query(x.float(), mode)
        assert (gd.double() - d).abs()[away].max() <= grid.cell
        cos = torch.nn.functional.cosine_similarity(gg.double(), g, dim=-1)
        assert cos[away & smooth].min() > 0.95
    # outside the grid the value keeps growing with the distance to the grid box (close to the true distance
    # where the nearest object is well inside the grid: the extra boxes)
    objs, grid, _ = warehouse_grids[1]
    far = torch.tensor([[3.0, 0.0, 0.3]])
    assert grid.query(far, mode)[0].item() == pytest.approx(objs.sdf(far.double()).item(), abs=0.03)


def test_environment_combines_fixed_and_extra():
    t = load_task("EnvSimple2D-RobotPointMass2D")
    x = torch.as_tensor(_rng(7).uniform(-1, 1, (5000, 2)))
    d_all, g_all = t.env(True).sdf(x, grad=True)
    d_f, g_f = t.env(True).fixed.sdf(x, grad=True)
    d_e, g_e = t.env(True).extra.sdf(x, grad=True)
    torch.testing.assert_close(d_all, torch.minimum(d_f, d_e), rtol=0, atol=0)
    torch.testing.assert_close(g_all, torch.where((d_e < d_f)[:, None], g_e, g_f), rtol=0, atol=0)
    torch.testing.assert_close(t.env(False).sdf(x), d_f, rtol=0, atol=0)


# ------------------------------------------------------------------------------------------- fractions
# docs/PAPER_VS_CODE.md, "Expected free-space fractions" (large-N columns): training | extra
REFERENCE = {
    "EnvSimple2D-RobotPointMass2D": (
        {"inside": 0.1829, "dilated": 0.2445},
        {"inside": 0.2641, "dilated": 0.3636},
    ),
    "EnvNarrowPassageDense2D-RobotPointMass2D": (
        {"inside": 0.2817, "dilated": 0.3714},
        {"inside": 0.3519, "dilated": 0.4800},
    ),
    "EnvPlanar2Link-RobotPlanar2Link": (
        {"env": 0.4083, "self": 0.0, "either": 0.4083},
        {"env": 0.5534, "self": 0.0, "either": 0.5534},
    ),
    "EnvPlanar4Link-RobotPlanar4Link": (
        {"env": 0.5324, "self": 0.0487, "either": 0.5754},
        {"env": 0.6646, "self": 0.0487, "either": 0.7060},
    ),
    "EnvSpheres3D-RobotPanda": (
        {"env": 0.3069, "self": 0.0312, "either": 0.3375},
        {"env": 0.5647, "self": 0.0312, "either": 0.5851},
    ),
    "EnvWarehouse-RobotPanda": (
        {"env": 0.2052, "self": 0.0312, "either": 0.2312},
        {"env": 0.2490, "self": 0.0312, "either": 0.2751},
    ),
}
WORKSPACE_ONLY = {
    "EnvPlanar2Link-RobotPlanar2Link": (0.1142, 0.1300),
    "EnvPlanar4Link-RobotPlanar4Link": (0.1336, 0.1649),
}


@pytest.mark.parametrize("name", TASKS)
def test_collision_fractions_match_reference(name):
    """Acceptance: 100,000 samples per scene, within 0.01 of the reference (its standard error is ~0.0015)."""
    got = collision_fractions(load_task(name), n=100_000, seed=0)
    want = {f"{s}/{k}": v for s, ref in zip(("train", "extra"), REFERENCE[name]) for k, v in ref.items()}
    assert set(got) == set(want)
    bad = {k: (round(got[k], 4), v) for k, v in want.items() if abs(got[k] - v) > 0.01}
    assert not bad, bad


@pytest.mark.parametrize("name", list(WORKSPACE_ONLY))
def test_planar_workspace_fractions(name):
    t = load_task(name)
    x = torch.as_tensor(_rng(8).uniform(-1, 1, (100_000, 2)))
    for extra, want in zip((False, True), WORKSPACE_ONLY[name]):
        assert (t.env(extra).sdf(x) < 0).double().mean().item() == pytest.approx(want, abs=0.01)
