"""Benchmark: one MPD plan of 100 trajectories on EnvSpheres3D-RobotPanda with the Panda-sized network (the paper's
Fig. 9 setting: 15 DDIM steps, 3 guided steps x 4 inner steps = 12 cost-gradient steps, 128 dense points).

The network is randomly initialised: timing does not depend on the weights. Run with `nox -s benchmarks`; the
breakdown (network, cost gradient and each cost) is printed and stored in the benchmark's extra_info.
"""

from __future__ import annotations

import pytest
import torch

from mpd.models.checkpoint import LoadedModel, build_network
from mpd.models.normalizer import Normalizer
from mpd.planners import Context, make_planner
from mpd.tasks import load_task
from mpd.trajectory import make_parametrization

pytestmark = pytest.mark.benchmark


def panda_mpd(threads: int = 2):
    torch.set_num_threads(threads)
    task = load_task("EnvSpheres3D-RobotPanda")
    param = make_parametrization(task)
    torch.manual_seed(0)
    net = build_network("diffusion", task.dof, param.n_free, "goal_ee_pose", task.spec.model).eval()
    lo, hi = task.robot.q_min.float(), task.robot.q_max.float()
    norms = {"q_start": Normalizer(lo, hi), "ee_pos": Normalizer(-torch.ones(3), torch.ones(3))}
    meta = {
        "task_name": task.name,
        "parametrization": "bspline",
        "horizon": param.n_free,
        "dof": task.dof,
        "context_kind": "goal_ee_pose",
    }
    model = LoadedModel("diffusion", net.requires_grad_(False), Normalizer(lo, hi), norms, meta, path="<random>")
    planner = make_planner(
        "mpd", task, model=model, device="cpu", extra_objects=True, overrides={"guide_fraction": 0.2}
    )  # 3 guided DDIM steps x 4 = 12 gradient steps
    qs = torch.tensor([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    p, r = task.robot.ee_pose(torch.tensor([0.5, 0.3, -0.4, -2.0, 0.2, 2.0, 0.5], dtype=torch.float64))
    return planner, Context(qs, None, p.float(), r.float())


def test_mpd_plan_panda_spheres3d(benchmark):
    planner, ctx = panda_mpd()
    timings = []

    def run():
        timings.append(planner.plan(ctx, 100, seed=0).timings)

    benchmark.pedantic(run, rounds=5, warmup_rounds=1)
    t = timings[len(timings) // 2]
    assert int(t["cost_gradient_calls"]) == 12
    benchmark.extra_info.update({k: round(v, 4) for k, v in t.items()})
    print({k: round(v, 4) for k, v in t.items()})


def test_network_forward_panda_batch100(benchmark):
    planner, ctx = panda_mpd()
    net = planner.model.network
    cond = planner.model.normalize_context({"q_start": ctx.q_start, "ee_pos": ctx.ee_pos, "ee_rot": ctx.ee_rot})
    x = torch.randn(100, planner.param.n_free, 7)
    with torch.no_grad():
        benchmark.pedantic(lambda: net(x, 10, cond), rounds=20, warmup_rounds=2)
