"""Throughput of dataset generation: Panda paths in EnvWarehouse per second on one core.

One path = one context (start and goal from the pose regions by IK, or a random start) + RRTConnect +
simplifyMax + resampling + B-spline fit + the dense collision check of the fit: everything a worker does per
context. The target is >= 2 paths/s per core. The time split (contexts, planning) is in ``extra_info``.

Run: ``pytest benchmarks/test_bench_data.py -m benchmark --benchmark-only --benchmark-enable``
(``nox -s benchmarks``).
"""

from __future__ import annotations

import pytest
import torch

from mpd.data.definition import DatasetDefinition, resolve
from mpd.data.generate import compute_chunk

pytestmark = pytest.mark.benchmark

N_CONTEXTS = 20


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # one worker = one core
    yield
    torch.set_num_threads(n)


def test_warehouse_paths_per_second(benchmark):
    rd = resolve(
        DatasetDefinition(
            name="bench",
            task="EnvWarehouse-RobotPanda",
            n_contexts=N_CONTEXTS,
            chunk_size=N_CONTEXTS,
            seed=123,
        )
    )
    out = {}

    def run():
        out["arrays"], out["meta"] = compute_chunk(rd, 0)

    benchmark.pedantic(run, rounds=1, iterations=1, warmup_rounds=0)
    n_ok = int(out["arrays"]["success"].sum())
    meta = out["meta"]
    info = {
        "paths": n_ok,
        "contexts": N_CONTEXTS,
        "paths_per_s_per_core": n_ok / meta["wall_s"],
        # CPU time of the process: the per-core figure even while other processes compete for the cores
        "paths_per_cpu_s": n_ok / meta["cpu_s"],
        "context_s_mean": sum(meta["context_time"]) / N_CONTEXTS,
        "plan_s_mean": sum(meta["plan_time"]) / N_CONTEXTS,
    }
    benchmark.extra_info.update(info)
    print(
        f"\nEnvWarehouse: {n_ok}/{N_CONTEXTS} paths, {info['paths_per_s_per_core']:.2f} paths/s per core "
        f"(wall), {info['paths_per_cpu_s']:.2f} per CPU second; per context: contexts "
        f"{info['context_s_mean']:.3f} s, planning {info['plan_s_mean']:.3f} s"
    )
    assert n_ok >= N_CONTEXTS - 1
