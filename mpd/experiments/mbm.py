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
from mpd.paths import DATASETS_DIR

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


# the task the MBM priors are trained for (one for all families; datasets/mbm/)
PRIOR_TASK = DATASETS_DIR / "mbm" / "MBM-RobotPanda.toml"


@dataclass(frozen=True)
class PriorSettings:
    """A planner with a learned prior (``method``: mpd, dprior, dprior-cost, cvae, ...; any of ``mpd planners list``)
    on MBM's problems ``first``..``last`` of each family (the held-out half of ``datasets/mbm/MBM-RobotPanda-cpu``
    by default), each problem's scene given at plan time (:meth:`mpd.api.MotionPlanner.plan`), ``n_samples``
    trajectories per problem. ``model``: the prior's identity (or a prefix of it, or a checkpoint path)."""

    method: str = "mpd"
    model: str = ""
    n_samples: int = 100
    seed: int = 0
    first: int = 51
    last: int = 100
    cylinder_slabs: int = CYLINDER_SLABS
    grasp_target: str = "ignored"
    fast: bool = True  # the compiled network (bf16 where the CPU has it), mpd.api.load_planner's default
    # the collision cost's signed distance (PlannerSettings.sdf_mode): the nearest node of a grid, built for each
    # problem's scene (a truncated grid: mpd.envs.environment.PLAN_TIME_GRID_TRUNCATION), as in the paper
    sdf_mode: str = "nearest"

    def __post_init__(self):
        if self.grasp_target not in GRASP_TARGETS:
            raise ValueError(f"grasp_target {self.grasp_target!r} (one of {', '.join(GRASP_TARGETS)})")
        if not 1 <= self.first <= self.last <= 100:
            raise ValueError(f"problems {self.first}..{self.last}: need 1 <= first <= last <= 100")
        if self.n_samples < 1:
            raise ValueError(f"n_samples must be positive, got {self.n_samples}")

    @property
    def planner(self) -> str:
        return f"mpd_{self.method}"

    def planner_settings(self) -> str:
        return (
            f"model={self.model};n_samples={self.n_samples};fast={self.fast};problems={self.first}-{self.last};"
            f"cylinder_slabs={self.cylinder_slabs};grasp_target={self.grasp_target};sdf_mode={self.sdf_mode};"
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
    meta = {"baseline": "RRTConnect", "settings": asdict(settings), "mbm_identity": imported.identity}
    settings_file(out, meta, BaselineSettings)
    done = {(r["family"], r["index"]) for r in read_results(out)}
    fams = tuple(FAMILIES if families is None else families)
    todo = [(fam, p) for fam in fams for p in imported.problems(fam)[:limit] if (fam, p.index) not in done]
    return append_results(out, todo, lambda fam, p: run_problem(imported, fam, p, settings), progress)


def append_results(out: Path, todo: list, plan_one, progress=None) -> list[dict]:
    """Plan each (family, problem) of ``todo`` with ``plan_one``, appending its record to ``out/results.jsonl``
    (flushed and synced, so a killed run keeps what it planned) and this invocation's machine to
    ``provenance.json``; then every record of the folder."""
    if not todo:
        return read_results(out)
    record = record_machine(out)
    with open(out / RESULTS, "a") as fh:
        for fam, p in todo:
            rec = plan_one(fam, p)
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
            record(rec)
            if progress is not None:
                progress(rec)
    return read_results(out)


def settings_file(out: Path, meta: dict, cls) -> None:
    """Write ``settings.json``, or check that the folder's results were made with these settings (missing fields
    read as their defaults)."""
    path = out / "settings.json"
    if path.is_file():
        old = json.loads(path.read_text())
        same = old.get("baseline") == meta["baseline"] and old.get("mbm_identity") == meta["mbm_identity"]
        if not same or cls(**old["settings"]) != cls(**meta["settings"]):
            raise ValueError(f"{out} holds results of other settings ({old}); use another folder")
    else:
        _write_json(path, meta)


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


def record_machine(out: Path):
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
    "fraction_valid": "REAL",
    "problem": "INTEGER",
}


def _folder(out: Path) -> dict:
    """What a run folder contributes to a database: its planner, settings, records and machines."""
    meta = json.loads((out / "settings.json").read_text())
    if meta["baseline"] == "prior":
        s = PriorSettings(**meta["settings"])
        planner, timelimit = s.planner, 0.0
        seed_rule = f'problem_seed("mbm", {s.seed}, "<family>/<NNNN>") (mpd.data.planning), the plan\'s seed'
        label = f"{s.method} (model {meta.get('model_identity', s.model)}, {s.n_samples} samples)"
    else:
        s = BaselineSettings(**meta["settings"])
        planner, timelimit = PLANNER, s.time_limit
        seed_rule = f'problem_seed("mbm", {s.seed}, "<family>/<NNNN>") (mpd.data.planning), OMPL\'s seed'
        label = f"RRTConnect, limit {s.time_limit} s"
    return {
        "dir": out,
        "meta": meta,
        "settings": s,
        "planner": planner,
        "planner_settings": s.planner_settings(),
        "timelimit": timelimit,
        "seed_rule": seed_rule,
        "label": label,
        "records": read_results(out),
        "machines": read_provenance(out),
    }


def _run_attributes(r: dict) -> dict:
    first = r["time_first_s"]
    return {
        "time": first if first is not None else r["time_s"],
        "solved": r["success"],
        "status": _STATUS.get(r["status"], 0),
        "approximate_solution": False,
        "correct_solution": r["valid_mpd"],
        "simplification_time": r["time_s"] - first if first is not None and r["success"] else None,
        "solution_length": r["path_length"],
        "mpd_smoothness": r["smoothness"],
        "graph_states": r.get("n_vertices"),
        "valid_checks": r.get("checks"),
        "fraction_valid": r.get("fraction_valid"),
        "problem": r["index"],
    }


def write_database(
    out_dir: str | Path,
    db_path: str | Path | None = None,
    more: tuple[str | Path, ...] = (),
    problems: tuple[int, int] | None = None,
) -> Path:
    """Run folders' results as an OMPL benchmark database (one experiment per family, one run per problem and
    folder; each folder a planner configuration: ``out_dir`` and the folders of ``more``, e.g. RRTConnect beside
    MPD). ``time`` is the time to the first solution (RRTConnect's solve; a prior's whole plan; the rejection of an
    invalid start or goal), ``correct_solution`` mpd's checker's verdict on the path (a prior: on its best
    trajectory), ``fraction_valid`` a prior's valid share of its batch. The ``experiments`` table names the CPUs the
    runs planned on (``provenance.json``), OMPL's version, the base seed and the time limit (0: none); the same,
    with the per-problem seeds' rule and the counts, goes to the JSON sidecar ``benchmark.json`` beside the
    database. ``problems``: (first, last) keeps the runs of those problem indices only (e.g. the held-out half that
    both an RRTConnect folder of all 100 and a prior's folder hold)."""
    import mpd

    out = Path(out_dir)
    folders = [_folder(Path(d)) for d in (out, *more)]
    if problems is not None:
        for f in folders:
            f["records"] = [r for r in f["records"] if problems[0] <= r["index"] <= problems[1]]
    machines = [m for f in folders for m in f["machines"]]
    here = machine() if not machines else None
    cpus = sorted({m["cpu"] for m in machines}) if machines else [here["cpu"]]
    hosts = sorted({m["hostname"] for m in machines}) if machines else [here["hostname"]]
    ompls = sorted({m["ompl"] for m in machines}) if machines else [here["ompl"]]
    stamps = [(f["dir"] / RESULTS).stat().st_mtime for f in folders if (f["dir"] / RESULTS).is_file()]
    date = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(max(stamps) if stamps else time.time()))
    seeds = sorted({f["settings"].seed for f in folders})
    exps = []
    counts: dict[str, dict] = {}
    for fam in FAMILIES:
        runs, total = [], 0.0
        for f in folders:
            rows = sorted((r for r in f["records"] if r["family"] == fam), key=lambda r: r["index"])
            if not rows:
                continue
            counts.setdefault(f["planner"], {})[fam] = {
                "problems": len(rows),
                "solved": sum(bool(r["success"]) for r in rows),
                "valid_mpd": sum(bool(r["valid_mpd"]) for r in rows),
                "timeout": sum(r["status"] in ("timeout", "budget") for r in rows),
                "invalid_start": sum(r["status"] == "invalid_start" for r in rows),
                "invalid_goal": sum(r["status"] == "invalid_goal" for r in rows),
            }
            runs += [(f["planner"], f["planner_settings"], _run_attributes(r)) for r in rows]
            total += float(sum(r["time_s"] for r in rows))
        if not runs:
            continue
        s0 = folders[0]["settings"]
        exps.append(
            benchmark_db.Experiment(
                name=f"mbm_panda_{fam}",
                timelimit=max(f["timelimit"] for f in folders),
                version=" + ".join(f"OMPL {v}" for v in ompls),
                hostname=" + ".join(hosts),
                cpuinfo=" + ".join(cpus),
                date=date,
                seed=" ".join(str(x) for x in seeds),
                setup=(
                    f"MotionBenchMaker {fam} (Panda), mpd {mpd.__version__}, "
                    f"problems {imported_note(folders[0]['meta'])}; "
                    f"sphere model, cylinders as {s0.cylinder_slabs} boxes, grasped object {s0.grasp_target}; "
                    + "; ".join(f"{f['planner']}: {f['label']}, seeds {f['seed_rule']}" for f in folders)
                    + "; time to the first solution (RRTConnect's timeouts depend on the CPU)"
                ),
                totaltime=total,
                attributes=ATTRIBUTES,
                runs=runs,
                parameters={"family": fam, "grasp_target": s0.grasp_target},
            )
        )
    db = benchmark_db.write(out / "benchmark.db" if db_path is None else db_path, exps)
    sidecar = {
        "database": db.name,
        "planners": [
            {
                "planner": f["planner"],
                "folder": str(f["dir"]),
                "baseline": f["meta"]["baseline"],
                "planner_settings": f["planner_settings"],
                "settings": asdict(f["settings"]),
                "model_identity": f["meta"].get("model_identity"),
                "seeds": f["seed_rule"],
            }
            for f in folders
        ],
        "time_limit_note": "RRTConnect stops at the limit: which problems time out depends on the CPU and its load",
        "mbm_identity": folders[0]["meta"]["mbm_identity"],
        "ompl": ompls,
        "cpus": cpus,
        "machines": machines or [here],
        "date": date,
        "families": counts,
    }
    if len(folders) == 1:  # the single-folder sidecar's fields, as before
        f = folders[0]
        sidecar.update(
            baseline=f["meta"]["baseline"],
            planner=f["planner"],
            planner_settings=f["planner_settings"],
            settings=asdict(f["settings"]),
            seed=f["settings"].seed,
            seeds=f["seed_rule"],
            families=counts[f["planner"]],
        )
        if isinstance(f["settings"], BaselineSettings):
            sidecar["time_limit_s"] = f["settings"].time_limit
    _write_json(db.with_name(SIDECAR), sidecar)
    return db


def imported_note(meta: dict) -> str:
    return f"import {meta['mbm_identity']}"
