"""Validity of configurations and trajectories: hand-made collision and limit cases, self collision against a
brute-force pair enumeration, and the grid-SDF mode against the analytic one away from surfaces."""

from __future__ import annotations

import math

import pytest
import torch

from mpd.collision import CollisionChecker
from mpd.tasks import load_task

F64 = torch.float64

TEMPLATE = """
schema_version = 1
name = "Hand-{robot}"
[environment]
dim = 2
workspace = [[-1.0, -1.0], [1.0, 1.0]]
[[environment.obstacles]]
type = "sphere"
centre = {centre}
radius = 0.2
[[environment.extra_objects]]
type = "box"
centre = [-0.5, 0.0]
size = [0.2, 0.4]
[robot]
name = "{robot}"
[context]
kind = "goal_joint_position"
[trajectory]
duration = 2.0
n_control_points = 12
[collision]
cost_margin = 0.02
[costs.weights]
collision = 1.0
"""


def _task(tmp_path, robot: str, centre=(0.0, 0.0)):
    p = tmp_path / f"{robot}.toml"
    p.write_text(TEMPLATE.format(robot=robot, centre=list(centre)))
    return load_task(p)


def _line(a, b, n: int = 64) -> torch.Tensor:
    s = torch.linspace(0, 1, n, dtype=F64)[:, None]
    return torch.as_tensor(a, dtype=F64) * (1 - s) + torch.as_tensor(b, dtype=F64) * s


def test_point_mass_cases(tmp_path):
    """A disc of radius 0.02, one ball of radius 0.2 at the origin (+ a box at x = -0.5 as extra object)."""
    t = _task(tmp_path, "RobotPointMass2D")
    chk = CollisionChecker(t)
    q = torch.tensor([[0.0, 0.0], [0.219, 0.0], [0.221, 0.0], [0.0, -0.25], [-0.5, 0.0]], dtype=F64)
    assert chk.configs(q).valid.tolist() == [False, False, True, True, True]
    # clearance sdf - r: what a margin is compared with
    torch.testing.assert_close(chk.env_clearance(q[2:4]), torch.tensor([0.001, 0.03], dtype=F64))
    assert chk.configs(q, margin=0.01).valid.tolist() == [False, False, False, True, True]
    assert CollisionChecker(t, margin=0.01).configs(q).valid.tolist() == [False, False, False, True, True]
    assert CollisionChecker(t, extra_objects=True).configs(q).valid.tolist() == [
        False,
        False,
        True,
        True,
        False,
    ]
    paths = torch.stack(
        [_line([-0.9, 0.5], [0.9, 0.5]), _line([-0.9, 0.0], [0.9, 0.0]), _line([0.3, -0.9], [0.3, 0.9])]
    )
    v = chk.trajectories(paths)
    assert v.env_free.tolist() == [True, False, True] and v.valid.tolist() == [True, False, True]
    # a single point of a dense path in collision makes the path invalid
    paths[0, 40] = torch.tensor([0.1, 0.1], dtype=F64)
    assert not chk.trajectories(paths[:1]).valid.item()
    # leaving the position limits (the workspace box for a point mass)
    out = _line([0.5, 0.5], [1.05, 0.5])[None]
    v = chk.trajectories(out)
    assert v.env_free.item() and not v.pos_ok.item() and not v.valid.item()
    # no velocity or acceleration limits for the point mass
    huge = torch.full_like(out, 1e3)
    v = chk.trajectories(_line([0.5, 0.5], [0.9, 0.5])[None], huge, huge)
    assert v.vel_ok.item() and v.acc_ok.item() and v.valid.item()


def test_arm_limits(tmp_path):
    """Planar 2-link arm (reach 0.5 m), obstacle out of reach: only the limits decide."""
    t = _task(tmp_path, "RobotPlanar2Link", centre=(0.85, 0.85))
    chk = CollisionChecker(t)
    n = 50
    q = _line([-1.0, 0.5], [1.0, -0.5], n)[None].repeat(6, 1, 1)
    dq = torch.full_like(q, 2.1)  # limits: 2.175 rad/s, 15 rad/s^2, joint 2 within [-2.6, 2.6]
    ddq = torch.full_like(q, -14.9)
    dq[1, 10, 0] = 2.2
    dq[2, 49, 1] = -2.18
    ddq[3, 0, 1] = 15.01
    q[4, 25, 1] = 2.61
    q[5, 25, 1] = 2.59
    v = chk.trajectories(q, dq, ddq)
    assert v.collision_free.all()
    assert v.vel_ok.tolist() == [True, False, False, True, True, True]
    assert v.acc_ok.tolist() == [True, True, True, False, True, True]
    assert v.pos_ok.tolist() == [True, True, True, True, False, True]
    assert v.valid.tolist() == [True, False, False, False, False, True]
    v = chk.trajectories(q)  # without derivatives only positions and collisions count
    assert v.valid.tolist() == [True, True, True, True, False, True]
    # within reach of the arm: a ball at (0.4, 0) hit by the stretched arm
    t2 = _task(tmp_path, "RobotPlanar2Link", centre=(0.45, 0.0))
    assert CollisionChecker(t2).configs(torch.tensor([[0.0, 0.0], [math.pi / 2, 0.0]], dtype=F64)).valid.tolist() == [
        False,
        True,
    ]


def _brute_force_self(robot, q: torch.Tensor) -> torch.Tensor:
    """Self collision from the robot file's link pairs, enumerated here: any sphere of link a against b's."""
    c = robot.sphere_centres(q)
    r = robot.sphere_radii
    hit = torch.zeros(q.shape[0], dtype=torch.bool)
    for a, b in robot.spec.self_collision.link_pairs:
        for i, la in enumerate(robot.sphere_links):
            for j, lb in enumerate(robot.sphere_links):
                if la == a and lb == b:
                    hit |= (c[:, i] - c[:, j]).norm(dim=-1) < r[i] + r[j]
    return hit


@pytest.mark.parametrize("name", ["EnvPlanar4Link-RobotPlanar4Link", "EnvWarehouse-RobotPanda"])
def test_self_collision_vs_brute_force(name):
    t = load_task(name)
    q = t.robot.random_q(3000, torch.Generator().manual_seed(0))
    hit = _brute_force_self(t.robot, q)
    assert 0.01 < hit.float().mean() < 0.2
    assert torch.equal(~CollisionChecker(t).configs(q).self_free, hit)


def test_self_collision_off_by_task(tmp_path):
    """Planar4Link folded onto itself: a self collision when the task checks it, not otherwise."""
    folded = torch.tensor([[0.0, 2.3, 2.3, 2.3]], dtype=F64)
    t = load_task("EnvPlanar4Link-RobotPlanar4Link")
    assert _brute_force_self(t.robot, folded).item()
    assert not CollisionChecker(t).configs(folded).self_free.item()
    own = _task(tmp_path, "RobotPlanar4Link", centre=(0.9, 0.9))  # self_collision defaults to false
    assert CollisionChecker(own).configs(folded).self_free.item()


@pytest.mark.parametrize("mode", ["nearest", "trilinear"])
@pytest.mark.parametrize(
    "name, extra", [("EnvPlanar4Link-RobotPlanar4Link", True), ("EnvSimple2D-RobotPointMass2D", False)]
)
def test_grid_mode_agrees_away_from_surfaces(name, extra, mode):
    t = load_task(name)
    exact = CollisionChecker(t, extra)
    grid = CollisionChecker(t, extra, sdf_mode=mode)
    q = t.robot.random_q(20_000, torch.Generator().manual_seed(1))
    cell = t.spec.environment.sdf_cell_size
    # nearest-node error <= half a cell diagonal (the SDF is 1-Lipschitz): decisions can differ only closer
    c = t.robot.sphere_centres(q)
    clear = (exact.env.sdf(c) - t.robot.sphere_radii).abs().min(-1).values
    away = clear > cell
    assert away.float().mean() > 0.5
    a, b = exact.configs(q[away]), grid.configs(q[away].float())
    assert torch.equal(a.env_free, b.env_free)
    # and the clearances themselves agree to a cell
    assert (exact.env_clearance(q[away]) - grid.env_clearance(q[away].float()).double()).abs().max() <= cell


@pytest.mark.slow
def test_grid_mode_agrees_away_from_surfaces_panda():
    """Same for the Panda in the Warehouse (builds the 1.6 M-node workspace grid)."""
    t = load_task("EnvWarehouse-RobotPanda")
    exact, grid = CollisionChecker(t), CollisionChecker(t, sdf_mode="nearest")
    q = t.robot.random_q(20_000, torch.Generator().manual_seed(2))
    c = t.robot.sphere_centres(q)
    away = (exact.env.sdf(c) - t.robot.sphere_radii).abs().min(-1).values > t.spec.environment.sdf_cell_size
    assert torch.equal(exact.configs(q[away]).env_free, grid.configs(q[away].float()).env_free)


def test_authors_grid_lookup_reads_the_node_they_read():
    """The authors' lookup (a measurement of how many verdicts it would flip): n = ceil(extent / cell) nodes at
    linspace(lo, hi, n), node index clamp(round((x - lo) / extent * n), 0, n - 1), values the exact SDF there;
    written out here with numpy for points at chosen places."""
    import numpy as np

    task = load_task("EnvSimple2D-RobotPointMass2D")
    env = task.env(True)
    lo, hi = (np.asarray(v, dtype=np.float64) for v in env.workspace)
    cell = env.spec.sdf_cell_size
    n = np.ceil((hi - lo) / cell).astype(int)
    rng = np.random.default_rng(0)
    x = np.concatenate([lo + rng.random((200, 2)) * (hi - lo), [lo, hi, hi + 0.3, lo - 0.3]])
    idx = np.clip(np.round((x - lo) / (hi - lo) * n).astype(int), 0, n - 1)
    nodes = lo + idx * (hi - lo) / (n - 1)
    ref = env.sdf(torch.as_tensor(nodes)).numpy()
    got = env.sdf(torch.as_tensor(x), mode="authors").numpy()
    assert np.allclose(got, ref, atol=1e-12)
    # the read node drifts up to one node beyond the nearest one along each axis: mostly the nearest one in the
    # lower quarter, mostly the next one in the upper quarter
    near = np.clip(np.round((x - lo) / ((hi - lo) / (n - 1))).astype(int), 0, n - 1)
    off = (idx - near)[:200, 0]
    frac = (x[:200, 0] - lo[0]) / (hi[0] - lo[0])
    assert set(np.unique(off)) <= {0, 1}
    assert off[frac < 0.25].mean() < 0.5 < off[frac > 0.75].mean()
    # their cost reads the value and the gradient of that same node (sdf_mode = "authors" of the collision cost)
    d, g = env.sdf(torch.as_tensor(x), grad=True, mode="authors")
    ref_d, ref_g = env.sdf(torch.as_tensor(nodes), grad=True)
    assert np.allclose(d.numpy(), ref_d.numpy(), atol=1e-12) and np.allclose(g.numpy(), ref_g.numpy(), atol=1e-12)


def test_the_collision_cost_with_the_authors_lookup_reads_their_node():
    """The collision cost in sdf_mode "authors" (a measurement of the authors' cost field): for the point mass, value
    sum_n w_n relu(r + eps - d(q_n)) and gradient -w_n grad d(q_n) where active, with d and grad d read at their node
    (checked above against numpy), written out here; the nearest-node cost differs."""
    from mpd.costs.base import CostInput
    from mpd.costs.collision import CollisionCost
    from mpd.trajectory import make_parametrization

    task = load_task("EnvNarrowPassageDense2D-RobotPointMass2D")
    param, env = make_parametrization(task), task.env(False)
    gen = torch.Generator().manual_seed(0)
    free = torch.rand(64, param.n_free, task.dof, generator=gen, dtype=torch.float64) * 1.6 - 0.8
    q0, q1 = torch.full((64, 2), -0.8, dtype=torch.float64), torch.full((64, 2), 0.8, dtype=torch.float64)
    dense = param.dense(free, q0, q1)
    cost = CollisionCost(task)
    term = cost(CostInput(dense, task, env, None, "authors"))
    w = cost.weights(CostInput(dense, task, env, None, "authors"))  # (n,) quadrature weights
    d, g = env.sdf(dense.q, grad=True, mode="authors")  # (B, n), (B, n, 2)
    depth = task.robot.sphere_radii[0] + task.spec.collision.cost_margin - d
    assert (depth > 0).any() and (depth <= 0).any()
    assert torch.allclose(term.value, (depth.clamp_min(0) * w).sum(-1), rtol=1e-10)
    assert torch.allclose(term.g_q, -(depth > 0).double()[..., None] * w[:, None] * g, rtol=1e-10, atol=1e-14)
    nearest = cost(CostInput(dense, task, env, None, "nearest"))
    assert not torch.allclose(term.value, nearest.value)
