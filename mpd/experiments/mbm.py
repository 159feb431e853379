"""Baselines on the imported MotionBenchMaker problems (:mod:`mpd.data.mbm`): OMPL RRTConnect, mpd's data planner,
with a time limit per problem, each problem's own scene given at plan time.

Per problem: ``success`` (a path that passed the planner's own check), ``status``, ``time_first_s`` (RRTConnect's
first solution; it stops there), ``time_s`` (with simplification, resampling and the check), ``path_length``
(joint space, of the simplified path resampled to the task's ``n_points``), ``smoothness`` (mpd's: the sum of the
acceleration norms, by finite differences of that path timed over the task's duration) and ``valid_mpd``: the path
checked by mpd's ground-truth checker (:class:`mpd.collision.CollisionChecker`) at every ``check_step`` of joint
space along it. Results are appended, one JSON line per problem, to ``results.jsonl``: a rerun skips the problems
already there (resumable), and :func:`write_database` turns them into an OMPL benchmark database.

Reproducibility. Each problem's seed is ``problem_seed("mbm", seed, "<family>/<NNNN>")`` (recorded per problem);
RRTConnect is deterministic given it, but it stops at the time limit, so which problems time out depends on the CPU
and on what else the machine runs. Each invocation of :func:`run_baseline` appends what it ran on (CPU model, host,
threads, OMPL, mpd, torch, git commit) to ``provenance.json``; the database's ``experiments`` table and its JSON
sidecar (``benchmark.json``) carry the machines, the OMPL version, the seeds and the time limit.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mpd.data import benchmark_db
from mpd.data.mbm import CYLINDER_SLABS, FAMILIES, GRASP_TARGETS, Imported, grasp_points, grasped_object

RESULTS = "results.jsonl"
PROVENANCE = "provenance.json"
SIDECAR = "benchmark.json"
PLANNER = "geometric_RRTConnect"
# mpd's statuses onto OMPL's PlannerStatus (benchmark_db.STATUS)
_STATUS = {"ok": 6, "invalid_start": 1, "invalid_goal": 2, "timeout": 4, "budget": 4, "post_check": 6}


@dataclass(frozen=True)
class BaselineSettings:
    time_limit: float = 1.0  # seconds per problem
    check_step: float = 0.02  # rad of joint space between checked states (mpd's Panda default)
    seed: int = 0
    cylinder_slabs: int = CYLINDER_SLABS
    # the object a goal grasps: an obstacle like the others (the strict reading) or left out of the scene
    # (mpd.data.mbm's docstring; not comparable with numbers published on MBM)
    grasp_target: str = "obstacle"

    def __post_init__(self):
        if self.grasp_target not in GRASP_TARGETS:
            raise ValueError(f"grasp_target {self.grasp_target!r} (one of {', '.join(GRASP_TARGETS)})")

    def planner_settings(self) -> str:
        return (
            f"time_limit={self.time_limit};check_step={self.check_step};range=default;simplify=max;clearance=0;"
            f"grasp_target={self.grasp_target};"
        )


def _densify(q: np.ndarray, step: float) -> np.ndarray:
    """Every state of a polyline ``step`` apart on each edge (the ends included)."""
    out = [q[:1]]
    for a, b in zip(q[:-1], q[1:]):
        n = max(1, math.ceil(float(np.linalg.norm(b - a)) / step))
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def run_problem(imported: Imported, family: str, problem, settings: BaselineSettings) -> dict:
    """RRTConnect on one problem; the record of :data:`RESULTS`."""
    import torch

    from mpd.collision import CollisionChecker
    from mpd.data.checkers import SphereChecker
    from mpd.data.planning import JointSpacePlanner, PlannerSettings, PlanResult, problem_seed
    from mpd.metrics import path_length, smoothness
    from mpd.tasks import load_task

    task = load_task(imported.task_path(family))
    left_out = None
    if settings.grasp_target == "ignored":
        left_out = grasped_object(problem, grasp_points(task.robot, [problem.goal])[0])
    env = task.env().with_obstacles(problem.primitives(settings.cylinder_slabs, without=left_out))
    seed = problem_seed("mbm", settings.seed, problem.name)
    ps = PlannerSettings(time_limit=settings.time_limit, check_step=settings.check_step)
    n = task.spec.trajectory.n_points
    truth = CollisionChecker(task, env=env, margin=0.0)
    ends = truth.configs(torch.tensor([problem.start, problem.goal], dtype=torch.float64)).valid
    if not ends.all():
        # the planner's own checks leave out the joint limits (its state space holds them): a goal beyond them would
        # only run into the time limit
        status = "invalid_start" if not ends[0] else "invalid_goal"
        r = PlanResult(False, status, 0.0)
    else:
        planner = JointSpacePlanner(SphereChecker(task, clearance=0.0, env=env), ps, n)
        r = planner.plan(np.asarray(problem.start), np.asarray(problem.goal), seed)
    rec = {
        "family": family,
        "index": problem.index,
        "seed": seed,
        "left_out": left_out,
        "success": bool(r.success),
        "status": r.status,
        "time_first_s": float(r.stats.get("solve_s", r.time))
        if r.status not in ("invalid_start", "invalid_goal")
        else None,
        "time_s": float(r.time),
        "n_vertices": int(r.n_vertices),
        "checks": int(r.stats.get("checks", 0)),
        "path_length": None,
        "smoothness": None,
        "valid_mpd": None,
    }
    if r.path is not None:
        q = torch.as_tensor(r.path, dtype=torch.float64)[None]
        dt = task.spec.trajectory.duration / (n - 1)
        ddq = torch.zeros_like(q)
        ddq[:, 1:-1] = (q[:, 2:] - 2 * q[:, 1:-1] + q[:, :-2]) / dt**2
        rec["path_length"] = float(path_length(q)[0])
        rec["smoothness"] = float(smoothness(ddq)[0])
        dense = torch.as_tensor(_densify(r.path, settings.check_step), dtype=torch.float64)
        rec["valid_mpd"] = bool(truth.configs(dense).valid.all())
    return rec


def read_results(out_dir: str | Path) -> list[dict]:
    """The records of a run folder (a last line cut short by a killed run is ignored)."""
    f = Path(out_dir) / RESULTS
    if not f.is_file():
        return []
    out = []
    for line in f.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def run_baseline(
    imported: Imported,
    out_dir: str | Path,
    settings: BaselineSettings = BaselineSettings(),
    families: tuple[str, ...] | None = None,
    limit: int | None = None,
    progress=None,
) -> list[dict]:
    """RRTConnect on the problems of ``families`` (the first ``limit`` of each), appending to ``out_dir/results.jsonl``
    and skipping the problems already there (with the same settings: another setting needs another folder)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta_path = out / "settings.json"
    meta = {"baseline": "RRTConnect", "settings": asdict(settings), "mbm_identity": imported.identity}
    if meta_path.is_file():
        old = json.loads(meta_path.read_text())
        if old != meta:
            raise ValueError(f"{out} holds results of other settings ({old}); use another folder")
    else:
        tmp = meta_path.with_name(f"settings.json.tmp-{os.getpid()}")
        tmp.write_text(json.dumps(meta, indent=1) + "\n")
        os.replace(tmp, meta_path)
    done = {(r["family"], r["index"]) for r in read_results(out)}
    fams = tuple(FAMILIES if families is None else families)
    todo = [(fam, p) for fam in fams for p in imported.problems(fam)[:limit] if (fam, p.index) not in done]
    if not todo:
        return read_results(out)
    record = _record_machine(out)
    with open(out / RESULTS, "a") as fh:
        for fam, p in todo:
            rec = run_problem(imported, fam, p, settings)
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
            record(rec)
            if progress is not None:
                progress(rec)
    return read_results(out)


def machine() -> dict:
    """What a run plans on: CPU model, host, threads, OMPL's and the other libraries' versions, the git commit."""
    import torch

    from mpd.provenance import cpu_model, provenance

    prov = provenance()
    return {
        "cpu": cpu_model(),
        "hostname": platform.node(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
        "ompl": prov["libraries"].get("ompl", "missing"),
        "mpd": prov["mpd_version"],
        "git_commit": prov["git_commit"],
        "git_dirty": prov["git_dirty"],
        "libraries": prov["libraries"],
    }


def read_provenance(out_dir: str | Path) -> list[dict]:
    """The machines a run folder's results were planned on, one entry per invocation that planned something."""
    f = Path(out_dir) / PROVENANCE
    return json.loads(f.read_text())["invocations"] if f.is_file() else []


def _record_machine(out: Path):
    """Add this invocation to ``provenance.json`` (written again after each problem: its count and last time)."""
    entries = read_provenance(out)
    entry = {**machine(), "started": _now(), "finished": None, "problems": 0}
    entries.append(entry)

    def record(_rec: dict) -> None:
        entry["problems"] += 1
        entry["finished"] = _now()
        _write_json(out / PROVENANCE, {"invocations": entries})

    _write_json(out / PROVENANCE, {"invocations": entries})
    return record


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


ATTRIBUTES = {
    "time": "REAL",
    "solved": "BOOLEAN",
    "status": "ENUM",
    "approximate_solution": "BOOLEAN",
    "correct_solution": "BOOLEAN",
    "simplification_time": "REAL",
    "solution_length": "REAL",
    "mpd_smoothness": "REAL",
    "graph_states": "INTEGER",
    "valid_checks": "INTEGER",
    "problem": "INTEGER",
}


def write_database(out_dir: str | Path, db_path: str | Path | None = None) -> Path:
    """The run folder's results as an OMPL benchmark database (one experiment per family, one run per problem):
    ``time`` is the time to the first solution (to the rejection of an invalid start or goal),
    ``correct_solution`` mpd's checker's verdict on the path. The ``experiments`` table names the CPUs the runs
    planned on (``provenance.json``), OMPL's version, the base seed and the time limit; the same, with the
    per-problem seeds' rule and the counts, goes to the JSON sidecar ``benchmark.json`` beside the database."""
    import mpd

    out = Path(out_dir)
    meta = json.loads((out / "settings.json").read_text())
    s = BaselineSettings(**meta["settings"])
    recs = read_results(out)
    machines = read_provenance(out)
    here = machine() if not machines else None
    cpus = sorted({m["cpu"] for m in machines}) if machines else [here["cpu"]]
    hosts = sorted({m["hostname"] for m in machines}) if machines else [here["hostname"]]
    ompls = sorted({m["ompl"] for m in machines}) if machines else [here["ompl"]]
    date = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime((out / RESULTS).stat().st_mtime))
    seed_rule = f'problem_seed("mbm", {s.seed}, "<family>/<NNNN>") (mpd.data.planning), per problem in results.jsonl'
    exps = []
    counts = {}
    for fam in FAMILIES:
        rows = sorted((r for r in recs if r["family"] == fam), key=lambda r: r["index"])
        if not rows:
            continue
        counts[fam] = {
            "problems": len(rows),
            "solved": sum(bool(r["success"]) for r in rows),
            "valid_mpd": sum(bool(r["valid_mpd"]) for r in rows),
            "timeout": sum(r["status"] in ("timeout", "budget") for r in rows),
            "invalid_start": sum(r["status"] == "invalid_start" for r in rows),
            "invalid_goal": sum(r["status"] == "invalid_goal" for r in rows),
        }
        runs = []
        for r in rows:
            first = r["time_first_s"]
            runs.append(
                (
                    PLANNER,
                    s.planner_settings(),
                    {
                        "time": first if first is not None else r["time_s"],
                        "solved": r["success"],
                        "status": _STATUS.get(r["status"], 0),
                        "approximate_solution": False,
                        "correct_solution": r["valid_mpd"],
                        "simplification_time": r["time_s"] - first if first is not None and r["success"] else None,
                        "solution_length": r["path_length"],
                        "mpd_smoothness": r["smoothness"],
                        "graph_states": r["n_vertices"],
                        "valid_checks": r["checks"],
                        "problem": r["index"],
                    },
                )
            )
        exps.append(
            benchmark_db.Experiment(
                name=f"mbm_panda_{fam}",
                timelimit=s.time_limit,
                version=" + ".join(f"OMPL {v}" for v in ompls),
                hostname=" + ".join(hosts),
                cpuinfo=" + ".join(cpus),
                date=date,
                seed=s.seed,
                setup=(
                    f"MotionBenchMaker {fam} (Panda), mpd {mpd.__version__}, problems {imported_note(meta)}; "
                    f"sphere model, cylinders as {s.cylinder_slabs} boxes, grasped object {s.grasp_target}; "
                    f"seeds {seed_rule}; time to the first solution, limit {s.time_limit} s (timeouts depend on the "
                    "CPU)"
                ),
                totaltime=float(sum(r["time_s"] for r in rows)),
                attributes=ATTRIBUTES,
                runs=runs,
                parameters={"family": fam, "grasp_target": s.grasp_target},
            )
        )
    db = benchmark_db.write(out / "benchmark.db" if db_path is None else db_path, exps)
    sidecar = {
        "database": db.name,
        "baseline": meta["baseline"],
        "planner": PLANNER,
        "planner_settings": s.planner_settings(),
        "settings": asdict(s),
        "time_limit_s": s.time_limit,
        "time_limit_note": "RRTConnect stops at the limit: which problems time out depends on the CPU and its load",
        "seed": s.seed,
        "seeds": seed_rule,
        "mbm_identity": meta["mbm_identity"],
        "ompl": ompls,
        "cpus": cpus,
        "machines": machines or [here],
        "date": date,
        "families": counts,
    }
    _write_json(db.with_name(SIDECAR), sidecar)
    return db


def imported_note(meta: dict) -> str:
    return f"import {meta['mbm_identity']}"
