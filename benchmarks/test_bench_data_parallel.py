"""Data-parallel training throughput (mpd.models.data_parallel): one training step on one process against the same
step on two ranks, each on half the batch on its own core, the gradients averaged in shared memory. The compiled
step (mpd.models.compiled_step) as trainings run it, 1 thread per process, on random data of the real shapes, for
the 2-D network (EnvSimple2D-RobotPointMass2D) and the Panda one (EnvWarehouse-RobotPanda), each in the profile
given (``paper``: the authors' recipe, fp32; ``cpu``: bf16 where the CPU has it).

Both modes run in one test, interleaved: a round is some steps of the one-process training, then as many of the
two-rank training (while one runs, the other's processes wait), so that a change of the machine's load slows them
alike. Each training is a process of its own, started by the test (which only coordinates), so that each holds one
training state in its caches as a real training does. Reported: steps/s of each mode (medians over the rounds),
the wall-clock speedup, the steps per core-second of each (the two ranks use two cores), and the time rank 0 spends
averaging (writing its gradients, waiting for the other rank, summing):

``pytest benchmarks/test_bench_data_parallel.py -m benchmark --benchmark-enable -s`` (``nox -s benchmarks``).
Needs an otherwise idle machine with at least two cores.
"""

from __future__ import annotations

import math
import os
import statistics
import time

import pytest
import torch
from test_bench_training import _setup, _stepper

from mpd.device import resolve, training_request
from mpd.models import data_parallel as dp
from mpd.models.compiled_step import cxx_available

pytestmark = pytest.mark.benchmark

CASES = {"2d-paper": ("2d", "paper", 8, 40), "panda-cpu": ("panda", "cpu", 4, 8)}  # case, profile, rounds, steps


def _prepare(case: str, profile: str):
    task, _, _, data, shapes = _setup(case)
    spec, ts = task.model(profile), task.training(profile)
    return task, spec, ts, data, shapes


def _worker(conn, link: dp.Link | None, rank: int, case: str, profile: str) -> None:
    """One training (``link`` None) or one rank of the two-rank training: the same network, data and generator;
    runs the number of steps it receives and sends back the seconds they took, until it receives None."""
    torch.set_num_threads(1)
    _, spec, ts, data, shapes = _prepare(case, profile)
    stepper, gen = _stepper("compiled", spec, ts, shapes, resolve("cpu", training_request(ts.precision)))
    averaging: list[float] = []
    if link is not None:
        link.rank = rank
        stepper.shard = dp.Shard(link, ts.batch_size, stepper.params)
        average = stepper.shard.average

        def timed(loss):
            t0 = time.perf_counter()
            out = average(loss)
            averaging.append(time.perf_counter() - t0)
            return out

        stepper.shard.average = timed
    step = ts.ema_start  # past the EMA's start: its lerps every ema_every steps, as in most of a training
    while (n := conn.recv()) is not None:
        averaging.clear()
        t0 = time.perf_counter()
        for _ in range(n):
            xb, cb = data.batch(torch.randint(len(data), (ts.batch_size,), generator=gen))
            loss = stepper.on_batch(xb, cb, step, ts.lr)
            step += 1
        conn.send((time.perf_counter() - t0, float(loss), statistics.median(averaging) if averaging else 0.0))


@pytest.mark.parametrize("name", list(CASES))
def test_training_step_one_process_vs_two_ranks(benchmark, name):
    if not cxx_available():
        pytest.skip("torch.compile's CPU backend needs a C++ compiler")
    if (os.cpu_count() or 1) < 2:
        pytest.skip("two ranks need two cores")
    case, profile, rounds, per_round = CASES[name]
    task, spec, ts, _, shapes = _prepare(case, profile)
    arith = resolve("cpu", training_request(ts.precision))
    n_params = sum(p.numel() for p in _stepper("eager", spec, ts, shapes, arith)[0].params)
    ctx = torch.multiprocessing.get_context("spawn")
    link = dp.Link(2, n_params, ctx.Barrier(2))
    workers = {"one process": [(None, 0)], "two ranks": [(link, 0), (link, 1)]}
    conns, procs = {}, []
    for mode, roles in workers.items():
        for lk, rank in roles:
            ours, theirs = ctx.Pipe()
            procs.append(ctx.Process(target=_worker, args=(theirs, lk, rank, case, profile)))
            procs[-1].start()
            conns.setdefault(mode, []).append(ours)
    times: dict[str, list[float]] = {m: [] for m in workers}
    averaging: list[float] = []
    try:

        def run(mode: str, n: int) -> float:
            for c in conns[mode]:
                c.send(n)
            replies = [c.recv() for c in conns[mode]]
            if mode == "two ranks":
                averaging.append(replies[0][2])
            times[mode].append(max(r[0] for r in replies) / n)
            return replies[0][1]

        def one_round():
            return {m: run(m, per_round) for m in workers}

        for _ in range(2):  # the first compiles (the two ranks at once), then a warm-up round
            one_round()
        for m in times:
            times[m].clear()
        averaging.clear()
        losses = benchmark.pedantic(one_round, rounds=rounds, warmup_rounds=0)
    finally:
        for cs in conns.values():
            for c in cs:
                c.send(None)
        for p in procs:
            p.join(timeout=60)
            if p.is_alive():
                link.abort()
                p.terminate()
                p.join()
    assert all(p.exitcode == 0 for p in procs)
    median = {m: statistics.median(v) for m, v in times.items()}
    speedup = median["one process"] / median["two ranks"]
    info = dict(
        case=name, task=task.name, profile=profile, arithmetic=arith.dtype, batch=ts.batch_size, threads_per_rank=1,
        parameters=n_params, rounds=rounds, steps_per_round=per_round,
        one_process_steps_per_s=1 / median["one process"], two_ranks_steps_per_s=1 / median["two ranks"],
        wall_clock_speedup=speedup, steps_per_core_second_ratio=speedup / 2,
        rank0_averaging_ms=1000 * statistics.median(averaging),
    )  # fmt: skip
    print(
        f"\n{name} ({task.name}, {profile} profile, batch {ts.batch_size}, {arith.dtype}, 1 thread a process): "
        f"one process {info['one_process_steps_per_s']:.2f} steps/s, two ranks {info['two_ranks_steps_per_s']:.2f} "
        f"steps/s: {speedup:.2f}x in wall-clock time, {speedup / 2:.2f}x the steps per core-second; rank 0 "
        f"averages in {info['rank0_averaging_ms']:.1f} ms a step (median, waiting included)"
    )
    benchmark.extra_info.update(info)
    assert all(math.isfinite(v) for v in losses.values())
