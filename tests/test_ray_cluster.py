"""Every stage on a real Ray cluster: a two-node cluster started inside the test (``ray.cluster_utils.Cluster``; the
second node has a cache of its own, as on a cluster without a shared filesystem) runs a spec's dataset chunks,
training and planning, with the results of a local run; and a Ray worker killed in the middle of a dataset chunk
costs nothing that was finished."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest
import torch
from tiny import tiny_definition

pytestmark = pytest.mark.ray

REPO = Path(__file__).resolve().parents[1]
TASK = "EnvSimple2D-RobotPointMass2D"
METRICS = ["success", "fraction_valid", "vendi", "path_length", "smoothness", "best_index"]


def _spec(root: Path, definition: Path) -> Path:
    p = root / "cluster.toml"
    p.write_text(
        textwrap.dedent(f"""
        name = "cluster"
        n_contexts = 4
        n_samples = 16
        seeds = [0]
        record_contexts = 0
        [axes]
        task = ["{TASK}"]
        method = ["gp-cost", "dprior"]
        extra_objects = [false]
        [tasks."{TASK}"]
        dataset = "{definition}"
        profile = "cpu"
        train_steps = 20
        """)
    )
    return p


@pytest.mark.slow  # ~2 min on a quiet 2-core CPU (two Ray nodes start): run with -m slow
def test_a_spec_runs_data_training_and_planning_on_a_two_node_cluster(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    from mpd.experiments.results import read_results
    from mpd.experiments.runner import Runner
    from mpd.experiments.spec import load_spec

    monkeypatch.setenv("MPD_PRIORS", "none")
    monkeypatch.setenv("MPD_RUNS", str(tmp_path / "runs"))
    spec = _spec(tmp_path, tiny_definition(tmp_path / "c.toml", "c", TASK, 64, 16))  # 4 chunks

    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "local"))
    Runner(load_spec(spec), run_dir=tmp_path / "runs" / "local", progress=False).run()
    local = read_results(tmp_path / "runs" / "local")

    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "driver"))
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        # the second node's cache is not the driver's: everything it makes must reach the driver by value
        cluster.add_node(num_cpus=1, env_vars={"MPD_CACHE": str(tmp_path / "node2")})
        cluster.wait_for_nodes()
        Runner(
            load_spec(spec), executor="ray", address=cluster.address, run_dir=tmp_path / "runs" / "ray", progress=False
        ).run()
    finally:
        ray.shutdown()
        cluster.shutdown()
    on_ray = read_results(tmp_path / "runs" / "ray")

    key = ["cell_key", "context_index"]
    cols = [*key, *METRICS, "contexts_hash", "dataset_hash", "model_id", "plan_seed"]
    pd.testing.assert_frame_equal(
        local.sort_values(key).reset_index(drop=True)[cols], on_ray.sort_values(key).reset_index(drop=True)[cols]
    )
    man = json.loads((tmp_path / "runs" / "ray" / "manifest.json").read_text())
    nodes = man["ray_nodes"]
    assert len(nodes["units"]) == 2, f"planning ran on one node only: {nodes}"
    assert len(nodes["dataset_chunks"]) == 2 and sum(nodes["dataset_chunks"].values()) == 4, nodes
    assert sum(nodes["trainings"].values()) == 1, nodes
    # the driver's cache holds every chunk and the model, the same bytes as the local run's
    local_lock = json.loads(next((tmp_path / "local" / "datasets").glob("c-*/lock.json")).read_text())
    ray_lock = json.loads(next((tmp_path / "driver" / "datasets").glob("c-*/lock.json")).read_text())
    assert ray_lock["content_hash"] == local_lock["content_hash"]
    assert any((tmp_path / "node2").glob("datasets/c-*/chunk-*.npz")), "the second node computed no chunk"
    # the model the cluster trained is the local one (its file differs only in timings and provenance)
    from mpd.models.checkpoint import read_checkpoint

    (a,) = (tmp_path / "local" / "models").glob("*/*/model.pt")
    (b,) = (tmp_path / "driver" / "models").glob("*/*/model.pt")
    wa, wb = read_checkpoint(a)["ema_weights"], read_checkpoint(b)["ema_weights"]
    assert a.parent.name == b.parent.name and all(torch.equal(wa[k], wb[k]) for k in wa)


def _chunk_workers() -> list[int]:
    """Processes executing a dataset chunk task (Ray names a worker after the task it runs)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes()
            except OSError:
                continue
            if b"ray::_ray_chunk" in cmd:
                out.append(int(d.name))
    return out


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds Ray's workers in /proc")
def test_a_ray_worker_killed_during_a_chunk_loses_nothing_finished(tmp_path, monkeypatch):
    pytest.importorskip("ray")
    from mpd.data.definition import load_definition
    from mpd.data.generate import generate

    # NarrowPassage: a few planned paths per second, so that a chunk is still running when the kill comes
    defn = tiny_definition(tmp_path / "k.toml", "k", "EnvNarrowPassageDense2D-RobotPointMass2D", 48, 4)  # 12 chunks
    env = {**os.environ, "MPD_CACHE": str(tmp_path / "ray"), "PYTHONPATH": str(REPO), "MPD_PRIORS": "none"}
    cmd = [sys.executable, "-m", "mpd.cli", "data", "generate", str(defn), "--executor", "ray", "--workers", "2", "-q"]
    log = tmp_path / "generate.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    data_dir = tmp_path / "ray" / "datasets"
    finished: dict[str, int] = {}
    killed = None
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:
            sides = sorted(data_dir.glob("k-*/chunk-*.json"))
            workers = _chunk_workers()
            if len(sides) >= 2 and workers:
                finished = {str(p): p.stat().st_mtime_ns for p in sides}
                killed = workers[0]
                os.kill(killed, signal.SIGKILL)
                break
            time.sleep(0.05)
        assert killed is not None, "no chunk was running while others had finished:\n" + log.read_text()
        assert proc.wait(timeout=300) == 0, log.read_text()
    finally:
        if proc.poll() is None:  # never leave a Ray of this test running
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            subprocess.run([sys.executable, "-m", "ray.scripts.scripts", "stop", "--force"], capture_output=True)
    for path, mtime in finished.items():
        assert Path(path).stat().st_mtime_ns == mtime, f"{path}: a chunk finished before the kill was recomputed"
    ray_lock = json.loads(next(data_dir.glob("k-*/lock.json")).read_text())
    # the same chunks as a local generation, byte for byte
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "local"))
    local_lock = generate(load_definition(defn), workers=1, progress=False, create_lock=False)
    assert [o["sha256"] for o in ray_lock["outs"]] == [o["sha256"] for o in local_lock["outs"]]
