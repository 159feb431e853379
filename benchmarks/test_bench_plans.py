"""The four plans of the speed issue, in the setting the authors' planner is timed in (their code at 3676cbf):
100 samples, 15 DDIM steps (quadratic, eta 0.5), random weights of the authors' model sizes, 2 threads.

* ``mpd/panda``: MPD on EnvSpheres3D-RobotPanda with the extra objects, the authors' released models' 24 free
  control points (29 in all), guidance on the last 5 DDIM steps x 4 = 20 cost-gradient calls;
* ``prior/panda``: Dprior (no guidance), same task and network;
* ``mpd/simple2d`` and ``prior/simple2d``: EnvSimple2D-RobotPointMass2D (16 free control points), extra objects.

Each plan also runs with ``planner.network_precision = "bf16"`` where the CPU computes bfloat16 natively (fp32
everywhere: the fp32 path is always benchmarked), and with ``planner.network_compile`` (the U-Net compiled by
torch.compile with frozen weights; its compilation falls in the warm-up round). Medians of 7 rounds after one
warm-up; the planner's own breakdown (network, cost gradient, each cost) of the median round is stored in
``extra_info``, with the network's GFLOP per pass (torch's FLOP counter), its achieved GFLOP/s in the plan and the
fraction of this CPU's nominal peak for the plan's precision (``cpu_peak.py``).

Run: ``pytest benchmarks/test_bench_plans.py -m benchmark --benchmark-only --benchmark-enable`` (``nox -s
benchmarks``), alone on the machine: another process on the same cores makes every figure meaningless.
"""

from __future__ import annotations

import dataclasses
import statistics

import pytest
import torch
from cpu_peak import peak_gflops
from gpu_check import plan_context, random_model  # benchmarks/: the random-weight model and context of the GPU check

from mpd.device import native_bf16, network_precision
from mpd.executor import threads
from mpd.planners import make_planner
from mpd.tasks import load_task
from mpd.tasks.task import Task
from mpd.trajectory import make_parametrization

pytestmark = pytest.mark.benchmark

THREADS = 2
# the authors' released models: 18 desired control points -> 24 learnable + 5 fixed for the Panda (PAPER_VS_CODE.md)
AUTHORS_N_CONTROL = {"EnvSpheres3D-RobotPanda": 29, "EnvSimple2D-RobotPointMass2D": 22}
TASKS = {"panda": "EnvSpheres3D-RobotPanda", "simple2d": "EnvSimple2D-RobotPointMass2D"}
PRECISIONS = ["fp32"] + (["bf16"] if native_bf16(torch.device("cpu")) else [])


def authors_task(name: str) -> Task:
    """The task with the authors' released number of control points (the rest of its file unchanged)."""
    task = load_task(name)
    tr = dataclasses.replace(task.spec.trajectory, n_control_points=AUTHORS_N_CONTROL[name])
    return Task(dataclasses.replace(task.spec, trajectory=tr), task.path)


def bench_planner(task: Task, method: str, **settings):
    """MPD (``method="mpd"``) or Dprior (``"prior"``) on the task's extra-objects scene, a random-weight model of the
    authors' sizes, guidance on the last 30 % of the DDIM steps as in their configs, and these planner settings."""
    return make_planner(
        "mpd" if method == "mpd" else "dprior",
        task,
        model=random_model(task, make_parametrization(task)),
        device="cpu",
        extra_objects=True,
        overrides={"guide_fraction": 0.3, **settings},
    )


@pytest.fixture(autouse=True)
def two_threads():
    with threads(THREADS):
        yield


@pytest.mark.parametrize("network", ["eager", "compiled"])
@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("method", ["mpd", "prior"])
@pytest.mark.parametrize("which", list(TASKS))
def test_plan(benchmark, which, method, precision, network):
    task = authors_task(TASKS[which])
    if network == "compiled":
        # each compiled plan as in a process of its own: dynamo's caches hold no graphs of the earlier cases (the
        # U-Net forward's cache entries are shared by all its modules; a lookup walks past those of other models
        # and precisions, ~10-30 % of an EnvSimple2D pass with the other cases' graphs in front)
        torch._dynamo.reset()
    planner = bench_planner(task, method, network_precision=precision, network_compile=network == "compiled")
    ctx = plan_context(task, "cpu")
    timings = []

    def run():
        timings.append(planner.plan(ctx, 100, seed=0).timings)

    benchmark.pedantic(run, rounds=7, warmup_rounds=1)  # a compiled network compiles in the warm-up round
    runs = timings[1:]  # the warm-up's first
    walls = [t["total"] for t in runs]
    t = runs[walls.index(sorted(walls)[len(walls) // 2])]
    if method == "mpd":
        assert int(t["cost_gradient_calls"]) == 20
    benchmark.extra_info.update({k: round(float(v), 4) for k, v in t.items()})
    benchmark.extra_info["median_total_s"] = round(statistics.median(walls), 4)
    benchmark.extra_info["free_control_points"] = make_parametrization(task).n_free
    # the physical limit (issue 15, item 6): the network's FLOP rate in the plan against this CPU's nominal peaks
    gflop = network_gflop(planner, ctx)
    peak = peak_gflops(THREADS)
    rate = planner.settings.ddim_steps * gflop / t["network"]  # one pass per DDIM step
    benchmark.extra_info.update(
        network_gflop_per_pass=round(gflop, 4),
        network_gflop_per_s=round(rate, 1),
        peak_fp32_gflop_per_s=round(peak["fp32"], 1),
        peak_bf16_gflop_per_s=round(peak["bf16"], 1),
        fraction_of_peak=round(rate / peak[precision], 3),
    )


@pytest.mark.parametrize("method", ["mpd", "prior"])
@pytest.mark.parametrize("which", list(TASKS))
def test_plan_api_defaults(benchmark, which, method):
    """The same plans with the settings a user of the Python API gets without asking (``mpd.api.FAST_SETTINGS``:
    the compiled network, bf16 where the CPU has it): the first plan (compilation included, a fresh dynamo cache)
    and the steady state, the ratios of the speed acceptance against the authors' code."""
    import time

    from mpd.api import FAST_SETTINGS

    task = authors_task(TASKS[which])
    torch._dynamo.reset()
    planner = bench_planner(task, method, **FAST_SETTINGS)
    ctx = plan_context(task, "cpu")
    t0 = time.perf_counter()
    planner.plan(ctx, 100, seed=0)
    first = time.perf_counter() - t0
    timings = []
    benchmark.pedantic(lambda: timings.append(planner.plan(ctx, 100, seed=0).timings), rounds=7, warmup_rounds=0)
    walls = [t["total"] for t in timings]
    benchmark.extra_info.update(
        first_plan_s=round(first, 3),
        median_total_s=round(statistics.median(walls), 4),
        network_precision=network_precision(planner.settings.network_precision, "cpu"),
    )


def network_gflop(planner, ctx) -> float:
    """GFLOP of one denoising pass of the planner's network (batch 100, the context embedded once, as planned),
    counted by torch's FLOP counter on the eager network (its convolutions and products)."""
    from torch.utils.flop_counter import FlopCounterMode

    from mpd.planners.base import model_context

    net = planner.model.network
    x = torch.zeros(100, make_parametrization(planner.task).n_free, planner.task.dof)
    with torch.no_grad():
        emb = net.embed_context(planner.model.normalize_context(model_context(ctx)))
        with FlopCounterMode(display=False) as fc:
            net(x, 10, emb)
    return fc.get_total_flops() / 1e9


@pytest.mark.parametrize("which", list(TASKS))
def test_plan_time_obstacles(benchmark, which):
    """What obstacles given at plan time cost (MPD, compiled as the API runs it): per round a new obstacle set (two
    spheres at new places: the scene's grid of the extra set is rebuilt, ``scene_s``, then the plan) against a plan
    with the previous round's set (nothing rebuilt) and one without obstacles."""
    import time

    import numpy as np

    from mpd.api import FAST_SETTINGS
    from mpd.envs.primitives import Primitive

    task = authors_task(TASKS[which])
    torch._dynamo.reset()
    planner = bench_planner(task, "mpd", **FAST_SETTINGS)
    base = planner.env
    ctx = plan_context(task, "cpu")
    planner.plan(ctx, 100, seed=0)  # compiles
    rng = np.random.default_rng(0)
    lo, hi = base.workspace
    rounds = {"scene_s": [], "new_set_s": [], "same_set_s": [], "no_obstacles_s": []}

    def one_round():
        centres = rng.uniform(lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo), (2, task.dim))
        t0 = time.perf_counter()
        env = base.with_obstacles([Primitive("sphere", c, radius=0.05) for c in centres])
        env.grid("extra")
        planner.use_environment(env)
        rounds["scene_s"].append(time.perf_counter() - t0)
        rounds["new_set_s"].append(planner.plan(ctx, 100, seed=0).timings["total"])
        rounds["same_set_s"].append(planner.plan(ctx, 100, seed=0).timings["total"])
        planner.use_environment(base)
        rounds["no_obstacles_s"].append(planner.plan(ctx, 100, seed=0).timings["total"])

    benchmark.pedantic(one_round, rounds=5, warmup_rounds=0)
    benchmark.extra_info.update({k: round(statistics.median(v), 4) for k, v in rounds.items()})
