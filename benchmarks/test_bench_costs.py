"""Speed of one cost evaluation (values and gradient w.r.t. the free control points): the planner's hot path.

100 Panda trajectories x 128 points in EnvSpheres3D-RobotPanda, ``official`` preset, float32, nearest-node
SDF, CPU with 2 threads. Target: median <= 25 ms on the 2-core CPU. The inputs are straight joint-space lines
between random configurations plus noise (seeded), which cross many obstacles: 63 % of the configurations have
a sphere inside the collision margin, more than guided samples do, so this is the expensive end of the
collision cost. The second benchmark times the parts on their own (FK; environment collision and self
collision each given the kinematics), and the first one records the composite's own per-cost split in
``extra_info``.

Run: ``pytest benchmarks/test_bench_costs.py -m benchmark --benchmark-only --benchmark-enable``
(``nox -s benchmarks``).
"""

from __future__ import annotations

import statistics

import pytest
import torch

from mpd.costs import COSTS, CostFunction, CostInput
from mpd.executor import threads
from mpd.tasks import load_task
from mpd.trajectory import make_parametrization

pytestmark = pytest.mark.benchmark

B = 100
TASK = "EnvSpheres3D-RobotPanda"


@pytest.fixture(autouse=True)
def two_threads():
    with threads(2):
        yield


@pytest.fixture(scope="module")
def problem():
    task = load_task(TASK)
    param = make_parametrization(task, "bspline")
    env = task.env()
    r = task.robot
    g = torch.Generator().manual_seed(0)
    q_start, q_end = r.random_q(B, g, torch.float32), r.random_q(B, g, torch.float32)
    s = torch.linspace(0, 1, param.n_free)[None, :, None]
    free = q_start[:, None] * (1 - s) + q_end[:, None] * s
    free = free + 0.05 * torch.randn(free.shape, generator=g)
    ee_goal = r.ee_pose(r.random_q(B, g, torch.float32))
    env.grid("fixed")  # built once (~10 s), not part of an evaluation
    return task, param, env, (free, q_start, None, ee_goal)


def test_bench_costs_panda(benchmark, problem):
    task, param, env, args = problem
    cf = CostFunction(task, param, env, preset="official", sdf_mode="nearest")
    res = benchmark.pedantic(lambda: cf(*args), rounds=40, iterations=1, warmup_rounds=3)
    assert res.grad.shape == args[0].shape and torch.isfinite(res.grad).all()
    # where the time goes: the composite's own clock per cost (FK as its own entry), medians of 15 evaluations
    prof = CostFunction(task, param, env, preset="official", sdf_mode="nearest", profile=True)
    split = [prof(*args).timings for _ in range(15)]
    benchmark.extra_info.update({f"ms/{k}": 1e3 * statistics.median(t[k] for t in split) for k in split[0]})


@pytest.mark.parametrize("part", ["fk", "collision", "self_collision"])
def test_bench_costs_panda_parts(benchmark, problem, part):
    task, param, env, (free, q_start, q_goal, ee_goal) = problem
    dense = param.dense(free, q_start, q_goal)
    if part == "fk":
        q = dense.q.reshape(-1, task.dof)
        benchmark.pedantic(lambda: task.robot.kinematics(q, spheres=True, ee=False), rounds=40, warmup_rounds=3)
        return
    inp = CostInput(dense, task, env, ee_goal, "nearest")
    inp.kinematics()  # shared by all costs of an evaluation; timed above
    cost = COSTS[part](task, "official")
    term = benchmark.pedantic(lambda: cost(inp, 1.0), rounds=40, warmup_rounds=3)
    assert term.g_q is not None
