"""Training throughput of the diffusion priors on CPU: the step ``train_model`` runs (batch draw, loss forward and
backward, gradient clipping, fused AdamW, EMA), eager and with the loss compiled (mpd.models.compiled_step, with
inductor's C++ wrapper as trainings run it, and with its default Python wrapper for the ratio), for the 2-D network
(EnvSimple2D-RobotPointMass2D's ``cpu`` profile) and the Panda one (EnvWarehouse-RobotPanda's ``cpu`` profile), on
random data of the real shapes, 1 thread (as the trainings run, two side by side on a 2-core machine).

Each case reports steps/s, GFLOP per step (``torch.utils.flop_counter``: the convolutions and matrix products of the
forward and backward), the achieved GFLOP/s and its fraction of the nominal fp32 and bf16 peak of one core
(cpu_peak.py), the arithmetic the profile trains in here (bf16 autocast only where the CPU has native bf16) and, for
the compiled steps, the seconds their first call took (compilation). All modes of a network run in one process and
one test, interleaved (one step of each mode per round, each from its own copy of the same initial state), so that
a machine whose load changes during the run (the trainings beside it) slows them alike; the benchmark's own time is
the round's, the per-mode figures are the medians of each mode's steps (``extra_info``):

``pytest benchmarks/test_bench_training.py -m benchmark --benchmark-enable -s`` (``nox -s benchmarks``).
"""

from __future__ import annotations

import copy
import statistics
import time

import pytest
import torch
from cpu_peak import peak_gflops

from mpd.device import Arithmetic, resolve, training_request
from mpd.executor import threads
from mpd.models.compiled_step import CompiledStep, cxx_available
from mpd.models.context import context_shapes
from mpd.models.train import EagerStep, _Data, _init_network, make_optimizer, training_loss_kwargs
from mpd.tasks.task import load_task
from mpd.trajectory import make_parametrization

pytestmark = pytest.mark.benchmark

CASES = {"2d": "EnvSimple2D-RobotPointMass2D", "panda": "EnvWarehouse-RobotPanda"}
N_ROWS = 4096  # rows of the random training set the batches are drawn from
ROUNDS = {"2d": 40, "panda": 8}
MODES = ("eager", "compiled-python-wrapper", "compiled")  # the last: the training's own compiled step


class _Shapes:
    """What _init_network reads of a TrainingArrays."""

    def __init__(self, dof: int, horizon: int, context_kind: str):
        self.dof, self.horizon, self.context_kind = dof, horizon, context_kind


def _setup(case: str):
    task = load_task(CASES[case])
    spec, ts = task.model("cpu"), task.training("cpu")
    horizon = make_parametrization(task).n_free
    context_kind = "goal_ee_pose" if task.ee_goal else "goal_joint_position"
    g = torch.Generator().manual_seed(0)
    x = torch.rand(N_ROWS, horizon, task.dof, generator=g) * 2 - 1
    ctx = {
        k: torch.rand(N_ROWS, *shape, generator=g) * 2 - 1
        for k, shape in context_shapes(context_kind, task.dof).items()
    }
    if "ee_rot" in ctx:
        ctx["ee_rot"] = torch.linalg.qr(torch.randn(N_ROWS, 3, 3, generator=g)).Q
    return task, spec, ts, _Data(x, ctx), _Shapes(task.dof, horizon, context_kind)


@pytest.fixture(autouse=True)
def one_thread():
    with threads(1):
        yield


def _stepper(mode: str, spec, ts, shapes, arithmetic: Arithmetic):
    net = _init_network("diffusion", shapes, spec, 0).train()
    ema = copy.deepcopy(net).requires_grad_(False)
    opt = make_optimizer(net, ts)
    gen = torch.Generator().manual_seed(0)
    kw = training_loss_kwargs("diffusion", ts, torch.device("cpu"))
    args = ("diffusion", net, ema, opt, gen, ts, kw, arithmetic)
    if mode == "eager":
        return EagerStep(*args), gen
    if mode == "compiled-python-wrapper":  # inductor's default wrapper (the compiled step before INDUCTOR_OPTIONS)
        return CompiledStep(*args, inductor_options={}), gen
    return CompiledStep(*args), gen


@pytest.mark.parametrize("case", list(CASES))
def test_training_step_eager_vs_compiled(benchmark, case):
    from torch.utils.flop_counter import FlopCounterMode

    if not cxx_available():
        pytest.skip("torch.compile's CPU backend needs a C++ compiler")
    task, spec, ts, data, shapes = _setup(case)
    arith = resolve("cpu", training_request(ts.precision))
    arithmetic = arith.dtype
    steppers = {m: _stepper(m, spec, ts, shapes, arith) for m in MODES}
    times: dict[str, list[float]] = {m: [] for m in MODES}
    counter = [ts.ema_start]  # past the EMA's start: its lerps every ema_every steps, as in most of a training

    def one(mode: str) -> tuple[torch.Tensor, float]:
        stepper, gen = steppers[mode]
        t0 = time.perf_counter()
        xb, cb = data.batch(torch.randint(len(data), (ts.batch_size,), generator=gen))
        loss = stepper.on_batch(xb, cb, counter[0], ts.lr)
        return loss, time.perf_counter() - t0

    first = {m: one(m)[1] for m in MODES}  # the compiled step compiles here
    assert all(steppers[m][0].compiled for m in MODES[1:]), "a compiled step fell back to eager"
    net = steppers["eager"][0].net
    with FlopCounterMode(display=False) as fc:  # one eager step's operations (the compiled graph runs the same)
        one("eager")
    flops = fc.get_total_flops()

    def one_round():
        counter[0] += 1
        out = {}
        for m in MODES:
            out[m], dt = one(m)
            times[m].append(dt)
        return out

    for _ in range(2):  # warm-up rounds, not timed
        one_round()
    for m in MODES:
        times[m].clear()
    losses = benchmark.pedantic(one_round, rounds=ROUNDS[case], warmup_rounds=0)
    peak = peak_gflops(1)
    info = dict(
        case=case, task=task.name, arithmetic=arithmetic, precision=ts.precision, threads=1, batch=ts.batch_size,
        horizon=shapes.horizon, dof=shapes.dof, parameters=sum(p.numel() for p in net.parameters()),
        gflop_per_step=flops / 1e9, peak_fp32_gflop_per_s=peak["fp32"], peak_bf16_gflop_per_s=peak["bf16"],
        cpu=peak["cpu"], ghz=peak["ghz"],
    )  # fmt: skip
    print(f"\n{case} ({task.name}, cpu profile, batch {ts.batch_size}, {arithmetic} arithmetic, 1 thread):")
    for m in MODES:
        median = statistics.median(times[m])
        achieved = flops / 1e9 / median
        info[m] = dict(
            steps_per_s=1 / median, samples_per_s=ts.batch_size / median, gflop_per_s=achieved,
            fraction_of_fp32_peak=achieved / peak["fp32"], fraction_of_bf16_peak=achieved / peak["bf16"],
            first_call_s=first[m], rounds=len(times[m]),
        )  # fmt: skip
        print(
            f"  {m:>23}: {1 / median:.2f} steps/s, {flops / 1e9:.2f} GFLOP/step, {achieved:.1f} GFLOP/s = "
            f"{100 * achieved / peak['fp32']:.0f} % of the nominal fp32 peak of 1 core ({peak['fp32']:.0f} GFLOP/s), "
            f"{100 * achieved / peak['bf16']:.0f} % of bf16 ({peak['bf16']:.0f}); first call {first[m]:.1f} s"
        )
    info["speedup"] = statistics.median(times["eager"]) / statistics.median(times["compiled"])
    median = {m: statistics.median(times[m]) for m in MODES}
    info["cpp_wrapper_speedup"] = median["compiled-python-wrapper"] / median["compiled"]
    print(f"  compiled / eager: {info['speedup']:.2f}x; C++ / Python wrapper: {info['cpp_wrapper_speedup']:.3f}x")
    benchmark.extra_info.update(info)
    assert all(torch.isfinite(v) for v in losses.values())
