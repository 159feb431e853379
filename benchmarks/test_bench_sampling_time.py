"""The paper's "B-spline vs waypoints computation time" (Sec. V-F): denoising a batch of 1000 Panda trajectories
(d = 7, an end-effector goal) with 15 DDIM steps, as B-spline control points (n_b = 16 ... 64, then interpolated to
H = 128 dense points) or as H = 128 dense waypoints, the network of the Panda tasks (random weights: the time does
not depend on them). Each case: the prior's sampling (the network at the rows it models) plus the map to the 128
dense configurations, velocities and accelerations (for B-splines the interpolation, for waypoints the finite
differences); the costs are the same for both (they see the dense trajectory only) and are left out, as in the paper.

Run: ``pytest benchmarks/test_bench_sampling_time.py -m benchmark --benchmark-enable -s
--benchmark-json=out.json`` (part of ``nox -s benchmarks``); ``reports/sampling-time-bspline-waypoints/plot.py``
draws the figure from the JSON.
"""

from __future__ import annotations

import pytest
import torch

from mpd.models import DiffusionModel
from mpd.models.diffusion import sample
from mpd.tasks.spec import ModelSpec
from mpd.trajectory import BSplineTrajectory, WaypointTrajectory

pytestmark = pytest.mark.benchmark

PANDA = ModelSpec(unet_dim=32, unet_dim_mults=[1, 2, 4, 8], context_dim=128, context_layers=2)
DOF, BATCH, H = 7, 1000, 128
CASES = [("bspline", n) for n in (16, 24, 32, 48, 64)] + [("waypoints", H)]


@pytest.fixture(params=[2], ids=lambda n: f"threads{n}")
def threads(request):
    old = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(old)


@pytest.mark.parametrize(("kind", "n"), CASES, ids=[f"{k}{n}" for k, n in CASES])
def test_sample_1000_panda_trajectories(benchmark, threads, kind, n):
    param = (
        BSplineTrajectory(n, 5, H, 10.0, ee_goal=True) if kind == "bspline" else WaypointTrajectory(n, H, 10.0, True)
    )
    torch.manual_seed(0)
    model = DiffusionModel(DOF, param.n_free, "goal_ee_pose", PANDA).eval()
    g = torch.Generator().manual_seed(0)
    ctx = {
        "q_start": torch.rand(1, DOF, generator=g) * 2 - 1,
        "ee_pos": torch.rand(1, 3, generator=g),
        "ee_rot": torch.linalg.qr(torch.randn(1, 3, 3, generator=g)).Q,
    }
    q_start = ctx["q_start"].expand(BATCH, -1)

    def run():
        with torch.no_grad():
            free = sample(model, ctx, BATCH, steps=15, generator=torch.Generator().manual_seed(1))
            return param.dense(free, q_start)

    dense = benchmark.pedantic(run, rounds=3, warmup_rounds=1)
    benchmark.extra_info.update(
        parametrization=kind, n_params=n, n_free_rows=param.n_free, batch=BATCH, dense_points=H, ddim_steps=15,
        threads=threads, network_parameters=sum(p.numel() for p in model.parameters()),
    )  # fmt: skip
    assert dense.q.shape == (BATCH, H, DOF)
