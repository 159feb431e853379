"""Dataset generation: contexts, OMPL paths and B-spline fits, chunk by chunk, in parallel and resumable.

Each chunk (a fixed range of context indices) is computed by one worker process and written atomically
(:mod:`mpd.data.storage`). Generation skips every chunk that is already finished and verified, so an
interrupted run resumes where it stopped and never recomputes finished work. Results do not depend on the
number of workers: context i is drawn from a stream seeded by (seed, i) and OMPL is reseeded per problem.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from mpd import locks
from mpd.data.definition import GENERATOR_VERSION, ResolvedDefinition, load_definition
from mpd.data.storage import (
    chunk_name,
    chunk_record,
    clean_stale_temporaries,
    content_hash,
    npz_bytes,
    read_chunk,
    read_sidecar,
    remove_chunk,
    verify_chunk,
    write_atomic,
    write_chunk,
    write_chunk_bytes,
)
from mpd.executor import imap, report
from mpd.provenance import provenance
from mpd.schema import file_sha256

# stored as indices: new statuses go at the end
STATUSES = ("ok", "no_context", "invalid_start", "invalid_goal", "timeout", "post_check", "budget")
POST_CHECK_ATTEMPTS = 3

# ---------------------------------------------------------------------------------------------- worker side
_CACHE: dict[str, tuple] = {}


def _tools(rd: ResolvedDefinition):
    """Checker, sampler, planner, parametrization and ground-truth checker of a dataset, once per process."""
    if rd.identity not in _CACHE:
        from mpd.collision import CollisionChecker
        from mpd.data.checkers import make_checker
        from mpd.data.contexts import ContextSampler
        from mpd.data.planning import JointSpacePlanner
        from mpd.trajectory import make_parametrization

        d, task = rd.definition, rd.task
        checker = make_checker(task, d.checker.kind, rd.clearance, False, d.checker.self_pairs)
        sampler = ContextSampler(task, checker, d.contexts.min_start_goal_distance, d.contexts.max_tries)
        planner = JointSpacePlanner(checker, d.planner, task.spec.trajectory.n_points, store_dtype=np.float32)
        _CACHE[rd.identity] = (
            checker,
            sampler,
            planner,
            make_parametrization(task, "bspline"),
            CollisionChecker(task, extra_objects=False, margin=0.0),
        )
    return _CACHE[rd.identity]


def problem_list(rd: ResolvedDefinition) -> list:
    """The benchmark problems a definition with ``[problems]`` takes its contexts from (context i: the i mod n-th),
    each with the object left out of its scene (``grasp_target = "ignored"``) or None."""
    key = ("problems", rd.identity)
    if key not in _CACHE:
        from mpd.data import mbm

        ps = rd.definition.problems
        imp = mbm.import_problems()
        out = []
        for fam in ps.families or mbm.FAMILIES:
            for p in imp.problems(fam):
                if ps.first <= p.index <= ps.last:
                    left = None
                    if ps.grasp_target == "ignored":
                        left = mbm.grasped_object(p, mbm.grasp_points(rd.task.robot, [p.goal])[0])
                    out.append((p, left))
        _CACHE[key] = out
    return _CACHE[key]


def _problem_tools(rd: ResolvedDefinition, k: int):
    """Planner and ground-truth checker of the k-th problem's own scene, once per process."""
    key = ("problem-tools", rd.identity, k)
    if key not in _CACHE:
        from mpd.collision import CollisionChecker
        from mpd.data.checkers import SphereChecker
        from mpd.data.planning import JointSpacePlanner

        d, task = rd.definition, rd.task
        p, left = problem_list(rd)[k]
        env = task.env().with_obstacles(p.primitives(d.problems.cylinder_slabs, without=left))
        checker = SphereChecker(task, clearance=rd.clearance, env=env)
        planner = JointSpacePlanner(checker, d.planner, task.spec.trajectory.n_points, store_dtype=np.float32)
        _CACHE[key] = (planner, CollisionChecker(task, env=env, margin=0.0))
    return _CACHE[key]


def compute_chunk(rd: ResolvedDefinition, i: int, progress=None) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays of chunk i and its run-dependent figures (times)."""
    import torch

    from mpd.data.contexts import ContextError, ee_goal_pose
    from mpd.data.planning import problem_seed

    d, task = rd.definition, rd.task
    checker, sampler, planner, param, truth = _tools(rd)
    start, stop = d.chunk_range(i)
    n, dof, T, K = (
        stop - start,
        task.dof,
        task.spec.trajectory.n_points,
        task.spec.trajectory.n_control_points,
    )
    out = {
        "context_id": np.arange(start, stop, dtype=np.int64),
        "q_start": np.full((n, dof), np.nan),
        "q_goal": np.full((n, dof), np.nan),
        "source": np.zeros(n, dtype=np.int8),
        "status": np.zeros(n, dtype=np.int8),
        "success": np.zeros(n, dtype=bool),
        "n_vertices": np.zeros(n, dtype=np.int16),
        "path": np.full((n, T, dof), np.nan, dtype=np.float32),
        "control_points": np.full((n, K, dof), np.nan, dtype=np.float32),
        "fit_in_range": np.zeros(n, dtype=bool),
        "fit_free": np.zeros(n, dtype=bool),
    }
    ctx_time, plan_time = np.zeros(n), np.zeros(n)
    t_chunk, cpu_chunk = time.perf_counter(), time.process_time()
    # every context from its own stream; their IK problems (end-effector goals) solved in batches: the same
    # contexts as one at a time. The sampling time of the chunk is spread evenly over its contexts.
    t0 = time.perf_counter()
    which = None  # per context, the index of its benchmark problem (definitions with [problems])
    if d.problems is not None:
        from mpd.data.contexts import SOURCES, SampledContext

        problems = problem_list(rd)
        which = np.arange(start, stop) % len(problems)
        src = SOURCES.index("problem")
        sampled = [
            SampledContext(np.asarray(problems[j][0].start), np.asarray(problems[j][0].goal), src) for j in which
        ]
    else:
        sampled = sampler.sample_many([np.random.default_rng([d.seed, idx]) for idx in range(start, stop)])
    ctx_time[:] = (time.perf_counter() - t0) / n
    for k, idx in enumerate(range(start, stop)):
        c = sampled[k]
        if isinstance(c, ContextError):
            out["status"][k] = STATUSES.index("no_context")
            _report(progress, False)
            continue
        out["q_start"][k], out["q_goal"][k], out["source"][k] = c.q_start, c.q_goal, c.source
        if which is not None:
            planner, truth_k = _problem_tools(rd, int(which[k]))
            ends = truth_k.configs(torch.as_tensor(np.stack([c.q_start, c.q_goal]), dtype=torch.float64)).valid
            if not ends.all():
                # a benchmark's start or goal may lie beyond mpd's joint limits, which OMPL only finds by running to
                # its time limit
                out["status"][k] = STATUSES.index("invalid_start" if not ends[0] else "invalid_goal")
                _report(progress, False)
                continue
        r = planner.plan(c.q_start, c.q_goal, problem_seed(d.seed, idx))
        plan_time[k] = r.time
        for attempt in range(1, POST_CHECK_ATTEMPTS):
            # a resampled state between two checked grid points failed the re-check (a path grazing the
            # clearance): plan again with another seed rather than store an unchecked path
            if r.status != "post_check":
                break
            r = planner.plan(c.q_start, c.q_goal, problem_seed(d.seed, idx, attempt))
            plan_time[k] += r.time
        out["status"][k] = STATUSES.index(r.status)
        out["n_vertices"][k] = r.n_vertices
        if r.success:
            out["success"][k] = True
            out["path"][k] = r.path
        _report(progress, r.success)
    ok = out["success"]
    if ok.any():
        # fit the stored (float32) paths and judge the stored (float32) control points
        w = param.fit(out["path"][ok].astype(np.float64)).astype(np.float32)
        out["control_points"][ok] = w
        lo, hi = task.robot.q_min.numpy(), task.robot.q_max.numpy()
        # the authors discard fits with a control point outside twice the joint range (centred on the range)
        in_range = ((w >= lo - (hi - lo) / 2) & (w <= hi + (hi - lo) / 2)).all(axis=(1, 2))
        out["fit_in_range"][ok] = in_range
        # (a path that could not be fitted has NaN control points: out of range above, and not collision free)
        fitted = np.flatnonzero(ok)[np.isfinite(w).all(axis=(1, 2))]
        if len(fitted):
            dense = torch.as_tensor(param.basis @ out["control_points"][fitted].astype(np.float64))
            if which is None:
                out["fit_free"][fitted] = truth.trajectories(dense).collision_free.numpy()
            else:  # each fit in its own problem's scene
                for j in np.unique(which[fitted]):
                    sel = which[fitted] == j
                    free = _problem_tools(rd, int(j))[1].trajectories(dense[torch.as_tensor(sel)]).collision_free
                    out["fit_free"][fitted[sel]] = free.numpy()
    if task.ee_goal:
        has = ~np.isnan(out["q_goal"][:, 0])
        out["ee_pos"] = np.full((n, 3), np.nan)
        out["ee_rot"] = np.full((n, 3, 3), np.nan)
        if has.any():
            out["ee_pos"][has], out["ee_rot"][has] = ee_goal_pose(task, out["q_goal"][has])
    meta = {
        "contexts": [start, stop],
        "successes": int(ok.sum()),
        "context_time": np.round(ctx_time, 6).tolist(),
        "plan_time": np.round(plan_time, 6).tolist(),
        "wall_s": round(time.perf_counter() - t_chunk, 4),
        # CPU time of this process: the per-core cost even when other processes compete for the cores
        "cpu_s": round(time.process_time() - cpu_chunk, 4),
    }
    return out, meta


def _report(progress, success: bool) -> None:
    if progress is not None:
        progress(success)


def _work(rd: ResolvedDefinition, i: int) -> dict:
    """Work item (this process or a pool worker): compute and write chunk i, reporting every finished context."""
    arrays, meta = compute_chunk(rd, i, lambda s: report(bool(s)))
    return write_chunk(rd.data_dir, i, arrays, meta)


# ---------------------------------------------------------------------------------------------- driver side
def _lock_chunks(rd: ResolvedDefinition) -> dict[int, str]:
    """Chunk hashes of the committed lock file, when it describes this identity."""
    try:
        lock = json.loads(rd.lock_path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}
    if lock.get("identity") != rd.identity:
        return {}
    return {int(o["chunk"]): o["sha256"] for o in lock.get("outs", [])}


def committed_lock(rd: ResolvedDefinition) -> dict | None:
    """The committed lock file's record when it describes this identity, else None."""
    try:
        lock = json.loads(rd.lock_path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    return lock if lock.get("identity") == rd.identity else None


def committed_content_hash(rd: ResolvedDefinition) -> str | None:
    """The content hash the committed lock file records for this identity (None without one): what generating the
    dataset gives, since a generation reproduces every chunk byte for byte."""
    lock = committed_lock(rd)
    return lock.get("content_hash") if lock else None


def chunk_states(rd: ResolvedDefinition, use_lock: bool = True) -> dict[int, str]:
    """Why each unfinished chunk is not usable ({} when the dataset is complete)."""
    expected = _lock_chunks(rd) if use_lock else {}
    bad = {}
    for i in range(rd.definition.n_chunks):
        ok, why = verify_chunk(rd.data_dir, i, expected.get(i))
        if not ok:
            bad[i] = why
    return bad


def _keep_if_lock_is_stale(rd: ResolvedDefinition, todo: dict[int, str], say) -> dict[int, str]:
    """``todo`` less the intact chunks that differ from the committed lock when the lock, not the chunks, is stale.

    An intact chunk (its archive matches its sidecar) can differ from the committed lock for two reasons: it was made
    by other code than this (regenerate it), or the lock was (a stale lock, or another CPU's arithmetic: keep it,
    regenerating gives the same bytes again). One of them is regenerated in memory to tell which: when it comes out
    byte for byte as the cached one, every such chunk is kept and the lock is rewritten when the dataset is complete
    (with the warning of `generate`); otherwise they are all regenerated, as before.
    """
    intact = sorted(i for i, why in todo.items() if why != "missing" and verify_chunk(rd.data_dir, i)[0])
    if not intact:
        return todo
    i = intact[0]
    arrays, _ = compute_chunk(rd, i)
    again = npz_bytes(arrays)
    if file_sha256(rd.data_dir / chunk_name(i)) != hashlib.sha256(again).hexdigest():
        say(
            f"{rd.name}: chunks {intact} differ from the committed lock and chunk {i} regenerates differently: "
            "they were made by other code; regenerating them"
        )
        return todo
    say(
        f"{rd.name}: chunks {intact} differ from the committed lock, but chunk {i} regenerates to the same bytes: "
        "the lock is stale (or was made on a CPU that computes differently); keeping them"
    )
    return {k: v for k, v in todo.items() if k not in intact}


def default_dataset(task_name: str) -> str:
    """``<task>-paper`` when that dataset is complete in this cache, else ``<task>-cpu`` (the Panda tasks' size for
    CPU-trained priors) when complete, else ``<task>-small``. A committed lock file alone does not count: a fresh
    clone would otherwise generate a large dataset first."""
    from mpd.data.definition import DATASETS_DIR

    for size in ("paper", "cpu"):
        name = f"{task_name}-{size}"
        if (DATASETS_DIR / f"{name}.toml").exists():
            rd = load_definition(name)
            if rd.data_dir.exists() and not chunk_states(rd):
                return name
    return f"{task_name}-small"


def generate(
    name_or_path: str | Path | ResolvedDefinition,
    workers: int | None = None,
    progress: bool = True,
    chunks: list[int] | None = None,
    log=None,
    create_lock: bool = True,
    executor: str = "local",
    address: str | None = None,
) -> dict:
    """Generate (or finish) a dataset; returns its lock record (also written next to the definition).

    Args:
        workers: processes (default: all cores); 1 runs in this process. With ``executor="ray"``: the CPUs of a
            local Ray when no ``address`` is given.
        executor: "local" (processes of this machine) or "ray": every chunk is a Ray task (one CPU), retried by Ray
            when its worker dies; its bytes come back through the object store, checked by sha256, and are written
            here (unless this cache already holds them: a shared cache). The chunks are the same, byte for byte.
        chunks: only these chunk indices (for tests and partial runs); the lock is written when all are done.
        create_lock: False: a lock file next to the definition is updated when it exists but never created (an
            experiment run writes only under its run folder and the cache; `mpd data generate` creates it).
    """
    rd = name_or_path if isinstance(name_or_path, ResolvedDefinition) else load_definition(name_or_path)
    say = log or (lambda m: print(m, file=sys.stderr))
    # one generation of a dataset at a time on a cache: a second process (another `mpd run` of a spec that needs the
    # same dataset) waits, then finds the chunks made and computes nothing again
    held = locks.hold(rd.data_dir, lambda: say(f"{rd.name}: another process is generating it; waiting"))
    try:
        return _generate(rd, say, workers, progress, chunks, create_lock, executor, address)
    finally:
        held.close()


def _generate(rd, say, workers, progress, chunks, create_lock, executor, address) -> dict:
    d = rd.definition
    rd.data_dir.mkdir(parents=True, exist_ok=True)
    clean_stale_temporaries(rd.data_dir)
    write_atomic(rd.data_dir / "definition.json", (json.dumps(_definition_record(rd), indent=1) + "\n").encode())
    todo = chunk_states(rd)
    todo = _keep_if_lock_is_stale(rd, todo, say)
    for i, why in sorted(todo.items()):
        if why != "missing":
            say(f"{rd.name}: {rd.data_dir.name}/chunk-{i:05d}: {why}; regenerating it")
            remove_chunk(rd.data_dir, i)
    pending = sorted(todo if chunks is None else set(todo) & set(chunks))
    n_ctx = sum(d.chunk_range(i)[1] - d.chunk_range(i)[0] for i in pending)
    if executor not in ("local", "ray"):
        raise ValueError(f"unknown executor {executor!r} (local, ray)")
    if workers is None:
        workers = os.cpu_count() or 1
    workers = max(1, min(int(workers), len(pending) or 1))
    t0 = time.perf_counter()
    if pending:
        done = d.n_contexts - sum(d.chunk_range(i)[1] - d.chunk_range(i)[0] for i in todo)
        if done:
            say(f"{rd.name}: resuming, {done} of {d.n_contexts} contexts already generated")
        if executor == "ray":
            from mpd import distributed

            distributed.init(address, workers)
            workers = distributed.cluster_cpus()
        _run(rd, pending, workers, n_ctx, progress, executor)
    wall = time.perf_counter() - t0
    if chunk_states(rd, use_lock=False):
        return {}
    lock, changed = _write_lock(rd, workers if pending else None, wall if pending else None, create_lock)
    if changed:
        say(
            f"{rd.name}: warning: chunks {changed} differ from the previous lock file of the same identity "
            "(the generation did not reproduce them)"
        )
    return lock


def _run(
    rd: ResolvedDefinition, pending: list[int], workers: int, n_ctx: int, progress: bool, executor: str = "local"
) -> None:
    from tqdm import tqdm

    bar = tqdm(total=n_ctx, desc=rd.name, unit="ctx", disable=not progress, smoothing=0.05, dynamic_ncols=True)
    t0, paths = time.perf_counter(), [0]

    def tick(success: bool) -> None:
        paths[0] += bool(success)
        bar.update(1)
        el = time.perf_counter() - t0
        bar.set_postfix_str(f"{paths[0] / max(el, 1e-9):.1f} paths/s", refresh=False)

    mode = "ray" if executor == "ray" else ("process" if workers > 1 else "serial")
    try:
        if mode == "ray":
            _run_ray(rd, pending, tick)
        else:
            # one thread per worker (and here): a chunk's bytes do not depend on how it was run
            items = [(rd, i) for i in pending]
            for _ in imap(_work, items, mode, workers, threads=1, progress=tick, name=_chunk_name):
                pass
    finally:
        bar.close()


def _chunk_name(item: tuple) -> str:
    rd, i = item
    return f"{rd.name} chunk {i}"


def _ray_chunk(rd: ResolvedDefinition, i: int) -> tuple[dict, bytes]:
    """Ray task: compute chunk i, write it in this worker's cache (atomically: a retry after a kill is safe) and
    return its sidecar record (with the node) and archive bytes for the driver."""
    from mpd import distributed

    arrays, meta = compute_chunk(rd, i)
    data = npz_bytes(arrays)
    record = chunk_record(i, data, dict(meta, node=distributed.node_id()))
    rd.data_dir.mkdir(parents=True, exist_ok=True)
    write_chunk_bytes(rd.data_dir, i, data, record)
    return record, data


def _run_ray(rd: ResolvedDefinition, pending: list[int], tick) -> None:
    from mpd.distributed import checked

    # an error raised by the code itself is not retried by Ray (it would fail again) and reaches the driver
    for (_, i), (record, data) in imap(_ray_chunk, [(rd, i) for i in pending], "ray", name=_chunk_name):
        checked(data, record["sha256"], f"{rd.name} chunk {i}")
        ok, _ = verify_chunk(rd.data_dir, i, record["sha256"])
        if not ok:  # not already here through a shared cache
            write_chunk_bytes(rd.data_dir, i, data, record)
        start, stop = record["contexts"]
        for k in range(stop - start):
            tick(k < record["successes"])


def _repo_relative(path: Path) -> str:
    from mpd.paths import REPO_ROOT

    p = Path(path).resolve()
    try:
        return str(p.relative_to(REPO_ROOT))
    except ValueError:
        return str(p)


def _definition_record(rd: ResolvedDefinition) -> dict:
    from mpd.data.definition import robot_file
    from mpd.schema import file_sha256

    rf = robot_file(rd.task)
    return {
        "name": rd.name,
        "identity": rd.identity,
        "generator_version": GENERATOR_VERSION,
        "definition": asdict(rd.definition),
        "task": {"name": rd.task.name, "path": _repo_relative(rd.task.path), "sha256": rd.task.file_hash},
        "robot": {"name": rd.task.robot.name, "path": _repo_relative(rf), "sha256": file_sha256(rf)},
    }


def _figures(rd: ResolvedDefinition, sides: list[dict], workers: int | None, wall: float | None) -> dict:
    d = rd.definition
    status = np.zeros(len(STATUSES), dtype=np.int64)
    ok = in_range = free = 0
    for i in range(d.n_chunks):
        c = read_chunk(rd.data_dir, i)
        status += np.bincount(c["status"], minlength=len(STATUSES))
        ok += int(c["success"].sum())
        in_range += int(c["fit_in_range"].sum())
        free += int((c["fit_free"] & c["fit_in_range"]).sum())
    core_s = float(sum(s["wall_s"] for s in sides))
    cpu_s = float(sum(s.get("cpu_s", 0.0) for s in sides))
    plan_t = np.concatenate([s["plan_time"] for s in sides])
    ctx_t = np.concatenate([s["context_time"] for s in sides])
    fig = {
        "contexts": d.n_contexts,
        "successes": ok,
        "failures": int(d.n_contexts - ok),
        "failures_by_status": {s: int(n) for s, n in zip(STATUSES, status) if s != "ok" and n},
        "fit_out_of_range": int(ok - in_range),
        "paths": 2 * in_range,  # stored forward paths with a usable fit, and their reversed copies
        "fit_collision_free_rate": round(free / in_range, 6) if in_range else None,
        "core_seconds": round(core_s, 2),
        "paths_per_s_per_core": round(ok / core_s, 4) if core_s else None,
        "cpu_seconds": round(cpu_s, 2),
        "paths_per_cpu_s": round(ok / cpu_s, 4) if cpu_s else None,
        "plan_time_s": {
            "median": round(float(np.median(plan_t)), 5),
            "mean": round(float(plan_t.mean()), 5),
            "max": round(float(plan_t.max()), 4),
        },
        "context_time_s_mean": round(float(ctx_t.mean()), 5),
        "checker": {
            "kind": d.checker.kind,
            "clearance": rd.clearance,
            "check_step": d.planner.check_step,
            **({"self_pairs": d.checker.self_pairs} if d.checker.kind == "meshes" else {}),
        },
    }
    if wall is not None:
        fig["wall_time_s"] = round(wall, 2)
        fig["workers"] = workers
    return fig


def _write_lock(
    rd: ResolvedDefinition, workers: int | None, wall: float | None, create: bool = True
) -> tuple[dict, list[int]]:
    """Write the lock file (next to the definition and in the data directory); returns it and the chunks whose
    hash differs from a previous lock of the same identity."""
    d = rd.definition
    sides = [read_sidecar(rd.data_dir, i) for i in range(d.n_chunks)]
    try:
        prev = json.loads(rd.lock_path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        prev = {}
    same = prev.get("identity") == rd.identity
    prev_outs = {o["chunk"]: o["sha256"] for o in prev.get("outs", [])} if same else {}
    generated_now = wall is not None
    if not generated_now and same:  # nothing generated now: keep the figures of the run that made the data
        wall, workers = prev.get("figures", {}).get("wall_time_s"), prev.get("figures", {}).get("workers")
    outs = [
        {
            "chunk": s["chunk"],
            "path": s["path"],
            "sha256": s["sha256"],
            "size": s["size"],
            "contexts": s["contexts"],
        }
        for s in sides
    ]
    lock = _definition_record(rd) | {
        "data_dir": f"datasets/{rd.data_dir.name}",
        "outs": outs,
        "content_hash": content_hash([o["sha256"] for o in outs]),
        "figures": _figures(rd, sides, workers, wall),
        "provenance": provenance() if generated_now or not same else prev.get("provenance", provenance()),
    }
    text = (json.dumps(lock, indent=1) + "\n").encode()
    write_atomic(rd.data_dir / "lock.json", text)
    # A generation that reproduces the committed lock's data leaves the committed file alone: only this machine's
    # timings and provenance would change, and a fresh clone would otherwise show a dirty tree in every run's
    # provenance. The cache-side lock.json keeps this generation's figures.
    if not (same and prev.get("content_hash") == lock["content_hash"]) and (create or rd.lock_path.exists()):
        rd.lock_path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(rd.lock_path, text)
    changed = [o["chunk"] for o in outs if o["chunk"] in prev_outs and prev_outs[o["chunk"]] != o["sha256"]]
    return lock, changed
