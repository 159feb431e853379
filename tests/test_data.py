"""Datasets: reproducible bytes, verified and resumable chunks, valid paths, evaluation contexts, errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from mpd.data.checkers import SphereChecker, make_checker, path_valid
from mpd.data.contexts import evaluation_contexts
from mpd.data.dataset import load_dataset
from mpd.data.definition import load_definition
from mpd.data.generate import chunk_states, generate
from mpd.data.storage import chunk_name, sidecar_name
from mpd.schema import ConfigError
from mpd.tasks import load_task

TINY = """name = "{name}"
task = "{task}"
n_contexts = {n}
chunk_size = {chunk}
seed = {seed}
"""


pytestmark = pytest.mark.usefixtures("one_thread")


def _define(
    directory: Path,
    name: str,
    task: str = "EnvSimple2D-RobotPointMass2D",
    n: int = 12,
    chunk: int = 4,
    seed: int = 7,
) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    p = directory / f"{name}.toml"
    p.write_text(TINY.format(name=name, task=task, n=n, chunk=chunk, seed=seed))
    return p


def _chunk_bytes(rd) -> list[bytes]:
    return [(rd.data_dir / chunk_name(i)).read_bytes() for i in range(rd.definition.n_chunks)]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A tiny EnvSimple2D dataset generated once in its own cache (one process)."""
    root = tmp_path_factory.mktemp("ref")
    mp = pytest.MonkeyPatch()
    mp.setenv("MPD_CACHE", str(root / "cache"))
    try:
        path = _define(root / "defs", "tiny")
        lock = generate(path, workers=1, progress=False)
        ref_bytes = _chunk_bytes(load_definition(path))
    finally:
        mp.undo()
    return path, lock, ref_bytes, root / "cache"


def test_same_seed_same_bytes_any_worker_count(reference, tmp_path, monkeypatch):
    path, lock, ref_bytes, _ = reference
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    p2 = _define(tmp_path / "defs", "tiny")
    lock2 = generate(p2, workers=2, progress=False)  # a process pool: results must not depend on it
    assert lock2["identity"] == lock["identity"]
    assert lock2["content_hash"] == lock["content_hash"]
    assert _chunk_bytes(load_definition(p2)) == ref_bytes
    assert [o["sha256"] for o in lock2["outs"]] == [o["sha256"] for o in lock["outs"]]
    assert set(lock2["outs"][0]) >= {"path", "sha256", "size"}
    assert lock2["figures"]["contexts"] == 12 and lock2["figures"]["workers"] == 2
    # another seed is another dataset
    p3 = _define(tmp_path / "defs3", "tiny", seed=8)
    assert load_definition(p3).identity != lock["identity"]


def test_reproduced_generation_leaves_the_committed_lock_alone(reference, tmp_path, monkeypatch):
    """A fresh clone regenerating a dataset with a committed lock must not dirty the working tree: same data, same
    lock bytes (only the cache-side copy records this machine's timings)."""
    path, lock, _, _ = reference
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    p2 = _define(tmp_path / "defs", "tiny")
    rd = load_definition(p2)
    committed = json.dumps(lock, indent=1) + "\n"
    rd.lock_path.write_text(committed)
    lock2 = generate(p2, workers=1, progress=False)
    assert lock2["content_hash"] == lock["content_hash"]
    assert rd.lock_path.read_text() == committed
    assert json.loads((rd.data_dir / "lock.json").read_text())["content_hash"] == lock["content_hash"]
    # a different dataset under the same name is a new version: its lock is written
    p3 = _define(tmp_path / "defs", "tiny", seed=8)
    generate(p3, workers=1, progress=False)
    assert json.loads(rd.lock_path.read_text())["identity"] != lock["identity"]


def test_truncated_chunk_detected_and_regenerated(reference, tmp_path, monkeypatch, capsys):
    _, lock, ref_bytes, _ = reference
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    p = _define(tmp_path / "defs", "tiny")
    generate(p, workers=1, progress=False)
    rd = load_definition(p)
    f = rd.data_dir / chunk_name(1)
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    assert "truncated" in chunk_states(rd)[1]
    ds = load_dataset(p, progress=False)
    err = capsys.readouterr().err
    assert "chunk-00001" in err and "regenerating" in err
    assert _chunk_bytes(rd) == ref_bytes
    assert ds.info["content_hash"] == lock["content_hash"]


def test_resume_at_chunk_granularity(reference, tmp_path, monkeypatch):
    _, lock, ref_bytes, _ = reference
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    p = _define(tmp_path / "defs", "tiny")
    generate(p, workers=1, progress=False, chunks=[0, 2])  # an interrupted run: chunks 0 and 2 finished
    rd = load_definition(p)
    assert sorted(chunk_states(rd)) == [1]
    before = {i: (rd.data_dir / chunk_name(i)).stat() for i in (0, 2)}
    # chunk 1 was being written when the process died: a temporary file and an archive without its sidecar
    (rd.data_dir / f"{chunk_name(1)}.tmp-999999999").write_bytes(b"partial")
    (rd.data_dir / chunk_name(1)).write_bytes(ref_bytes[1][:100])
    lock2 = generate(p, workers=1, progress=False)
    for i, st in before.items():  # finished chunks are never recomputed
        now = (rd.data_dir / chunk_name(i)).stat()
        assert (now.st_ino, now.st_mtime_ns) == (st.st_ino, st.st_mtime_ns)
    assert not list(rd.data_dir.glob("*.tmp-*"))
    assert lock2["content_hash"] == lock["content_hash"]


def test_resume_keeps_finished_chunks_when_the_committed_lock_is_stale(reference, tmp_path, monkeypatch, capsys):
    """A committed lock that this code (or this CPU) does not reproduce must not make a resumed generation throw away
    its finished chunks (they would come out the same again); chunks made by other code are still regenerated."""
    _, lock, ref_bytes, _ = reference
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    p = _define(tmp_path / "defs", "tiny")
    rd = load_definition(p)
    stale = json.loads(json.dumps(lock))
    for o in stale["outs"]:
        o["sha256"] = "0" * 64
    stale["content_hash"] = "1" * 64
    rd.lock_path.write_text(json.dumps(stale, indent=1) + "\n")
    generate(p, workers=1, progress=False, chunks=[0, 2])  # an interrupted run
    assert sorted(chunk_states(rd)) == [0, 1, 2]  # 0 and 2 differ from the stale lock, 1 is missing
    before = {i: (rd.data_dir / chunk_name(i)).stat() for i in (0, 2)}
    capsys.readouterr()
    lock2 = generate(p, workers=1, progress=False)
    err = capsys.readouterr().err
    assert "the lock is stale" in err and "keeping them" in err
    for i, st in before.items():
        now = (rd.data_dir / chunk_name(i)).stat()
        assert (now.st_ino, now.st_mtime_ns) == (st.st_ino, st.st_mtime_ns)
    assert lock2["content_hash"] == lock["content_hash"] and _chunk_bytes(rd) == ref_bytes
    assert json.loads(rd.lock_path.read_text())["outs"][0]["sha256"] == lock["outs"][0]["sha256"]  # rewritten
    assert not chunk_states(rd)

    # a finished chunk that this code does not make (an older generator, same identity) is regenerated
    from mpd.data.storage import read_chunk, write_chunk

    arrays = read_chunk(rd.data_dir, 2)
    arrays["control_points"] = arrays["control_points"] + 1e-3
    write_chunk(rd.data_dir, 2, arrays, {})
    assert "differs from the lock" in chunk_states(rd)[2]
    capsys.readouterr()
    generate(p, workers=1, progress=False)
    assert "made by other code" in capsys.readouterr().err
    assert _chunk_bytes(rd) == ref_bytes


def test_resume_after_killing_a_real_run(tmp_path, monkeypatch):
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    p = _define(tmp_path / "defs", "killed", task="EnvPlanar2Link-RobotPlanar2Link", n=30, chunk=3)
    rd_dir = tmp_path / "cache" / "datasets"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mpd.cli", "data", "generate", str(p), "--workers", "1", "-q"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.time() + 60
        while time.time() < deadline and not list(rd_dir.glob("*/chunk-0000[0-9].json")):
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    rd = load_definition(p)
    finished = [i for i in range(rd.definition.n_chunks) if i not in chunk_states(rd)]
    assert finished, "the killed run finished no chunk"
    stats = {i: (rd.data_dir / sidecar_name(i)).stat().st_mtime_ns for i in finished}
    lock = generate(p, workers=1, progress=False)
    assert lock and not chunk_states(rd)
    assert all((rd.data_dir / sidecar_name(i)).stat().st_mtime_ns == t for i, t in stats.items())


@pytest.mark.parametrize(
    "task_name, n",
    [
        ("EnvSimple2D-RobotPointMass2D", 12),
        ("EnvPlanar4Link-RobotPlanar4Link", 6),
        ("EnvWarehouse-RobotPanda", 3),
    ],
)
def test_stored_paths_valid_and_dataset_layout(task_name, n, reference, tmp_path, monkeypatch):
    if task_name.startswith("EnvSimple2D"):
        path = reference[0]
        monkeypatch.setenv("MPD_CACHE", str(reference[3]))
    else:
        monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
        path = _define(tmp_path / "defs", "tiny", task=task_name, n=n, chunk=n)
    rd = load_definition(path)
    ds = load_dataset(path, progress=False)
    task, d = rd.task, rd.definition
    checker = make_checker(task, d.checker.kind, rd.clearance)
    fwd = ~ds.reversed
    assert fwd.sum() == ds.info["figures"]["successes"] - ds.info["figures"]["fit_out_of_range"]
    for q in ds.paths[fwd]:  # every stored path is valid at the checker's resolution
        assert path_valid(checker, q.astype(np.float64), d.planner.check_step)
    # the reversed copies: same context, swapped ends, reversed path and control points, same split
    f, r = np.nonzero(fwd)[0], np.nonzero(~fwd)[0]
    assert np.array_equal(ds.context_id[f], ds.context_id[r]) and np.array_equal(ds.split[f], ds.split[r])
    assert np.array_equal(ds.paths[r], ds.paths[f][:, ::-1])
    assert np.array_equal(ds.control_points[r], ds.control_points[f][:, ::-1])
    assert np.array_equal(ds.q_start[r], ds.q_goal[f]) and np.array_equal(ds.q_goal[r], ds.q_start[f])
    assert np.allclose(ds.paths[:, 0], ds.q_start, atol=1e-6) and np.allclose(ds.paths[:, -1], ds.q_goal, atol=1e-6)
    assert ds.control_points.shape[1:] == (task.spec.trajectory.n_control_points, task.dof)
    if task.ee_goal:
        p, rot = task.robot.ee_pose(torch.as_tensor(ds.q_goal))
        assert np.allclose(ds.ee_pos, p.numpy()) and np.allclose(ds.ee_rot, rot.numpy())
    else:
        assert ds.ee_pos is None
    assert len(ds.subset("train")) + len(ds.subset("val")) + len(ds.subset("test")) == len(ds)


def test_evaluation_contexts_fixed(tmp_path, monkeypatch):
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    for name, n in [("EnvSimple2D-RobotPointMass2D", 5), ("EnvPlanar4Link-RobotPlanar4Link", 3)]:
        task = load_task(name)
        a = evaluation_contexts(task, n)
        b = evaluation_contexts(task, n)  # from the cache
        c = evaluation_contexts(task, n, refresh=True)  # recomputed
        for x in (b, c):
            assert np.array_equal(a.q_start, x.q_start) and np.array_equal(a.q_goal, x.q_goal)
        both = SphereChecker(task, extra_objects=True, clearance=task.spec.collision.clearance)
        assert both.valid(a.q_start).all() and both.valid(a.q_goal).all()
        dist = np.linalg.norm(a.q_goal - a.q_start, axis=1)
        assert (dist >= task.spec.context.min_start_goal_distance).all()
        assert (a.ee_pos is not None) == task.ee_goal
    assert len(list((tmp_path / "cache" / "contexts").glob("*.npz"))) == 2


@pytest.mark.parametrize(
    "body, field",
    [
        (
            'name = "bad"\ntask = "EnvSimple2D-RobotPointMass2D"\nn_contexts = 4\nchunk_sise = 2\n',
            "chunk_sise",
        ),
        ('name = "bad"\ntask = "EnvNoSuchTask"\nn_contexts = 4\n', "task"),
        (
            'name = "bad"\ntask = "EnvSimple2D-RobotPointMass2D"\nn_contexts = 4\n[planner]\ntime_limit = "x"\n',
            "planner.time_limit",
        ),
        (
            'name = "bad"\ntask = "EnvSimple2D-RobotPointMass2D"\nn_contexts = 4\n[planner]\nmax_checks = -1\n',
            "planner",
        ),
        ('name = "other"\ntask = "EnvSimple2D-RobotPointMass2D"\nn_contexts = 4\n', "name"),
        ('name = "bad"\ntask = "EnvSimple2D-RobotPointMass2D"\nn_contexts = 0\n', "n_contexts"),
    ],
)
def test_bad_definitions_give_one_clear_line(tmp_path, body, field):
    p = tmp_path / "bad.toml"
    p.write_text(body)
    with pytest.raises(ConfigError) as e:
        load_definition(p)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{p}: {field}"), msg


def test_cli_info_and_show(reference, tmp_path, monkeypatch):
    from click.testing import CliRunner

    from mpd.cli.data import data

    path, lock, _, cache = reference
    monkeypatch.setenv("MPD_CACHE", str(cache))
    r = CliRunner().invoke(data, ["info", str(path)])
    assert r.exit_code == 0, r.output
    assert lock["content_hash"] in r.output and "fit_collision_free_rate" in r.output
    r = CliRunner().invoke(data, ["info", str(path), "--json"])
    assert json.loads(r.output)["identity"] == lock["identity"]
    out = tmp_path / "paths.png"
    r = CliRunner().invoke(data, ["show", str(path), "--out", str(out), "--n", "5"])
    assert r.exit_code == 0, r.output
    assert out.stat().st_size > 1000


def test_paths_are_memory_mapped_and_read_where_indexed(reference, monkeypatch, capfd):
    """Loading keeps the dense paths in the chunk files (memory-mapped); every way of indexing them gives what the
    whole arrays, read the ordinary way (np.load), give; the waypoint fit block by block equals the fit at once."""
    from mpd.data.dataset import PathArray
    from mpd.data.storage import map_chunk, read_chunk
    from mpd.models.data import training_arrays
    from mpd.trajectory import make_parametrization

    path, _, _, cache = reference
    monkeypatch.setenv("MPD_CACHE", str(cache))
    rd = load_definition(path)
    for i in range(rd.definition.n_chunks):
        mapped, read = map_chunk(rd.data_dir, i), read_chunk(rd.data_dir, i)
        assert isinstance(mapped["path"], np.memmap) and set(mapped) == set(read)
        for k in read:
            assert mapped[k].dtype == read[k].dtype and np.array_equal(np.asarray(mapped[k]), read[k], equal_nan=True)
    chunks = [read_chunk(rd.data_dir, i) for i in range(rd.definition.n_chunks)]
    fwd = np.concatenate([c["path"][c["success"] & c["fit_in_range"]] for c in chunks])
    ref = np.concatenate([fwd, fwd[:, ::-1]])
    ds = load_dataset(path, progress=False)
    assert isinstance(ds.paths, PathArray) and ds.paths.shape == ref.shape and len(ds.paths) == len(ref)
    rng = np.random.default_rng(0)
    idx = rng.permutation(len(ref))[:7]
    mask = rng.random(len(ref)) < 0.5
    assert np.array_equal(np.asarray(ds.paths), ref)
    assert np.array_equal(ds.paths[idx], ref[idx]) and np.array_equal(ds.paths[mask], ref[mask])
    assert np.array_equal(ds.paths[3], ref[3]) and np.array_equal(ds.paths[-1, -1], ref[-1, -1])
    assert np.array_equal(ds.paths[:, 0], ref[:, 0]) and np.array_equal(ds.paths[2:5], ref[2:5])
    sub = ds.subset("train")
    assert np.array_equal(np.asarray(sub.paths), ref[ds.split == 0]) and np.array_equal(
        sub.paths[[0, -1]], ref[ds.split == 0][[0, -1]]
    )
    blocks = [b for _, _, b in ds.paths.blocks(size=5)]
    assert np.array_equal(np.concatenate(blocks), ref)
    param = make_parametrization(rd.task, "waypoints")
    x = training_arrays(rd.task, ds, "waypoints").x
    assert np.array_equal(x, np.ascontiguousarray(param.free_rows(param.fit(ref)), dtype=np.float32))
    # a chunk marked synthetic makes the whole dataset say so, loudly
    side = rd.data_dir / "chunk-00000.json"
    saved = side.read_text()
    try:
        side.write_text(json.dumps({**json.loads(saved), "synthetic": True}))
        capfd.readouterr()
        assert load_dataset(path, progress=False).info["synthetic"] is True
        assert "SYNTHETIC" in capfd.readouterr().err
    finally:
        side.write_text(saved)


def test_batched_context_sampling_is_one_context_at_a_time():
    """``sample_many`` solves the IK problems of many contexts in one batch per round; every context must be the
    one ``sample`` draws from the same stream alone (successes and ContextErrors alike)."""
    from mpd.data.contexts import ContextError, ContextSampler
    from mpd.data.generate import _tools

    rd = load_definition("EnvWarehouse-RobotPanda-small")
    checker, sampler = _tools(rd)[:2]
    rngs = lambda: [np.random.default_rng([5, i]) for i in range(8)]  # noqa: E731
    hard = ContextSampler(rd.task, checker, ik_restarts=4, ik_restarts_per_pose=8, max_poses=2)

    def one(s, r):
        try:
            return s.sample(r)
        except ContextError as e:
            return e

    for s in (sampler, hard):
        alone = [one(s, r) for r in rngs()]
        batch = s.sample_many(rngs())
        for a, b in zip(alone, batch):
            assert type(a) is type(b)
            if isinstance(a, ContextError):
                assert str(a) == str(b)
            else:
                assert a.source == b.source
                assert np.array_equal(a.q_start, b.q_start) and np.array_equal(a.q_goal, b.q_goal)
    assert {c.source for c in [one(sampler, r) for r in rngs()]} >= {1, 2}  # both IK kinds of context
    assert len({type(c) for c in hard.sample_many(rngs())}) == 2  # successes and failures


def test_a_check_budget_ends_a_problem_after_the_same_work_on_any_machine(tmp_path):
    """``planner.max_checks``: a problem not solved within the budget fails with status "budget" after the same
    checks whatever the time limit (so on a slow or busy machine too); one solved within it gives the very path the
    time limit alone gives (the budget changes no solved problem); a definition with ``max_checks = 0`` keeps the
    identity of one without the field, and a budget changes it."""
    import dataclasses

    from mpd.data.contexts import ContextSampler
    from mpd.data.planning import JointSpacePlanner, PlannerSettings, default_check_step, problem_seed

    task = load_task("EnvNarrowPassageDense2D-RobotPointMass2D")
    checker = make_checker(task, "spheres", task.spec.collision.clearance, False, "sphere_pairs")
    sampler = ContextSampler(task, checker)
    base = PlannerSettings(time_limit=10.0, check_step=default_check_step(task))
    n = task.spec.trajectory.n_points

    def plan(settings, c, i):  # (OMPL ignores a seed of 0: problem seeds are hashes)
        return JointSpacePlanner(checker, settings, n).plan(c.q_start, c.q_goal, problem_seed(3, i))

    for i in range(50):  # a problem that takes many checks (a straight connection takes a handful)
        c = sampler.sample(np.random.default_rng([3, i]))
        free = plan(base, c, i)
        if free.success and free.stats["solve_checks"] >= 200:
            break
    else:
        pytest.fail("no problem needing >= 200 checks among 50")
    needed = free.stats["solve_checks"]
    within = plan(dataclasses.replace(base, max_checks=10 * needed), c, i)
    assert within.status == "ok" and within.stats == {**free.stats, "solve_s": within.stats["solve_s"]}
    assert np.array_equal(within.path, free.path)
    short = [plan(dataclasses.replace(base, max_checks=needed // 4, time_limit=t), c, i) for t in (1000.0, 1.0)]
    assert [r.status for r in short] == ["budget", "budget"]
    assert short[0].stats["checks"] == short[1].stats["checks"] >= needed // 4
    assert short[0].stats["checks"] < needed

    ids = []
    for extra in ("", "[planner]\nmax_checks = 0\n", "[planner]\nmax_checks = 100000\n"):
        p = tmp_path / "budget.toml"
        p.write_text('name = "budget"\ntask = "EnvSimple2D-RobotPointMass2D"\nn_contexts = 4\n' + extra)
        ids.append(load_definition(p).identity)
    assert ids[0] == ids[1] != ids[2]


# the first chunk of each committed small dataset whose problems all solve well inside the time limit (a problem
# that runs into the limit may end differently on a faster or slower machine; see mpd.data.planning)
COMMITTED_CHUNKS = [
    ("EnvSimple2D-RobotPointMass2D-small", 0),
    ("EnvNarrowPassageDense2D-RobotPointMass2D-small", 0),
    ("EnvPlanar2Link-RobotPlanar2Link-small", 0),
    ("EnvPlanar4Link-RobotPlanar4Link-small", 1),
    ("EnvSpheres3D-RobotPanda-small", 0),
    ("EnvWarehouse-RobotPanda-small", 0),
]


@pytest.mark.parametrize("name, chunk", COMMITTED_CHUNKS)
def test_committed_lock_is_reproduced(name, chunk, tmp_path, monkeypatch):
    """A chunk regenerated from its definition has the sha256 its committed lock file records: the lock files
    are what a fresh clone's datasets are checked against (two Panda locks and one planar-arm lock were found
    stale this way: made before changes to the FK and to the planner that changed no definition)."""
    from mpd.data.generate import committed_lock
    from mpd.schema import file_sha256

    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    rd = load_definition(name)
    lock = committed_lock(rd)
    assert lock is not None, f"{name} has no committed lock"
    generate(rd, workers=1, progress=False, chunks=[chunk])
    assert file_sha256(rd.data_dir / chunk_name(chunk)) == lock["outs"][chunk]["sha256"]


_MKL_PROBE = """
import os, sys, tempfile
os.environ["MPD_CACHE"] = tempfile.mkdtemp()
from mpd.data.definition import load_definition
from mpd.data.generate import generate
from mpd.data.storage import chunk_name
from mpd.schema import file_sha256
rd = load_definition(sys.argv[1])
generate(rd, workers=1, progress=False, chunks=[0])
print(file_sha256(rd.data_dir / chunk_name(0)))
"""


@pytest.mark.parametrize("name", ["EnvWarehouse-RobotPanda-small", "EnvSpheres3D-RobotPanda-small"])
def test_generated_chunk_does_not_depend_on_the_processors_maths_library(name):
    """torch's products, solves, sin, cos and sqrt on the CPU run MKL kernels chosen by processor, which round
    differently on an Intel Xeon and an AMD EPYC (the committed Panda locks, made on one, were not reproduced on the
    other). A chunk made with MKL's portable code path (``MKL_CBWR=COMPATIBLE``) must have the bytes of one made
    with its default path: the data path's arithmetic (FK, IK, goal poses) does not go through MKL. On a processor
    where the two paths are the same this cannot fail; on an Intel Xeon with AVX-512 it failed before the fix (IK
    solutions differed by 8e-15, end-effector poses by 2e-16)."""
    shas = []
    for cbwr in (None, "COMPATIBLE"):
        env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
        if cbwr:
            env["MKL_CBWR"] = cbwr
        out = subprocess.run(
            [sys.executable, "-c", _MKL_PROBE, name], env=env, capture_output=True, text=True, check=True, timeout=600
        )
        shas.append(out.stdout.strip().splitlines()[-1])
    assert shas[0] == shas[1]


def test_every_committed_dataset_lock_is_the_identity_its_definition_resolves_to():
    """A committed lock (and the shipped digests and priors found through it) holds only while the definition, the
    task's data sections and the robot file (hashed byte for byte, comments included) are what made it: an edit of
    any of them, a comment in a robot file too, must not go unnoticed."""
    from mpd.data.definition import DATASETS_DIR

    locks = sorted(DATASETS_DIR.glob("*.lock.json"))
    assert len(locks) >= 10
    for lock_path in locks:
        name = lock_path.name.removesuffix(".lock.json")
        assert load_definition(name).identity == json.loads(lock_path.read_text())["identity"], name
