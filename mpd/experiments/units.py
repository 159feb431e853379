"""The unit of work of a run: one cell on one context. Executed in the runner's process, in a local process pool
or as a Ray task; everything it needs travels in a picklable :class:`Unit`, and the per-process cache keeps the
planner (model, SDF grids) of the cell it last ran."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

_CACHE: dict[tuple, Any] = {}
_MODELS: dict[tuple, Any] = {}  # the last model loaded, with its compiled network
_AUTHORS: dict[tuple, Any] = {}  # the last scene's checker with the authors' grid lookup (a 3-D grid: ~64 MB, seconds)


@dataclass
class Unit:
    cell_key: str
    params: dict[str, Any]  # the cell's axis values
    overrides: dict[str, Any]  # planner.* axes
    context_index: int
    context: dict[str, np.ndarray]  # q_start, q_goal (joint goal) or ee_pos/ee_rot (EE goal), q_goal_ref
    plan_seed: int
    model_path: str | None
    device: str
    record: bool = False
    provenance: dict[str, Any] = field(default_factory=dict)
    # (lo, hi) per joint: the normalized space of a planner without a model (the dataset's range)
    data_range: tuple[list[float], list[float]] | None = None
    task_path: str | None = None  # the task's file (a task given by path is not found by its name)
    fast: bool = False  # the diffusion network's fast path under the cell's own settings (SpecFile.fast)


@dataclass
class UnitResult:
    cell_key: str
    row: dict[str, Any]
    history: dict[str, np.ndarray] | None = None  # when recorded: the batch at every step, and the final dense


def _planner(unit: Unit):
    from mpd.models.checkpoint import load_model
    from mpd.planners import get_planner_class, make_planner
    from mpd.planners.settings import FAST_SETTINGS, fast_enabled
    from mpd.tasks import load_task

    key = (unit.cell_key, unit.model_path, unit.device, repr(unit.data_range))
    if key not in _CACHE:
        _CACHE.clear()  # one cell at a time per process: models and SDF grids can be large
        p = unit.params
        task = load_task(unit.task_path or p["task"])
        model = None
        if unit.model_path:
            mkey = (unit.model_path, unit.device, task.name, p["parametrization"])
            if mkey not in _MODELS:  # the cells of one model (Dprior, Dprior+Cost, MPD) share it: compiled once
                _MODELS.clear()
                _MODELS[mkey] = load_model(
                    unit.model_path,
                    expect_task=task.name,
                    expect_parametrization=p["parametrization"],
                    device=unit.device,
                )
            model = _MODELS[mkey]
        overrides = dict(unit.overrides)
        if unit.fast and get_planner_class(p["method"]).model_kind == "diffusion" and fast_enabled(unit.device):
            overrides = {**FAST_SETTINGS, **overrides}
        if p.get("sampler"):
            overrides["sampler"] = p["sampler"]
        planner = make_planner(
            p["method"],
            task,
            extra_objects=bool(p["extra_objects"]),
            rotation_deg=float(p["rotation_deg"] or 0.0),
            preset=p["preset"],
            overrides=overrides,
            parametrization=p["parametrization"] or "bspline",
            model=model,
            device=torch.device(unit.device),
            data_range=unit.data_range,
        )
        # compile before the first timed plan (nothing to do for an eager network); the seconds go to the row of the
        # plan that waited for them (time_warmup), 0 in every other row
        warm_s = planner.warmup(int(p["n_samples"])) if hasattr(planner, "warmup") else 0.0
        from mpd.collision import CollisionChecker

        checker = CollisionChecker(task, bool(p["extra_objects"]), float(p["rotation_deg"] or 0.0))
        # the authors' grid lookup, to count the verdicts it would flip (docs/PAPER_VS_CODE.md, "validity ground
        # truth"); one scene's grid is kept across its cells (a 3-D one costs seconds and ~64 MB to build)
        scene = (task.name, bool(p["extra_objects"]), float(p["rotation_deg"] or 0.0))
        if scene not in _AUTHORS:
            _AUTHORS.clear()
            _AUTHORS[scene] = CollisionChecker(task, scene[1], scene[2], sdf_mode="authors")
        _CACHE[key] = [task, planner, checker, _AUTHORS[scene], warm_s]
    return _CACHE[key]


def run_unit(unit: Unit) -> UnitResult:
    """Plan one context with one cell's planner and evaluate the batch with the ground-truth checker."""
    from mpd.metrics import evaluate
    from mpd.planners import Context

    entry = _planner(unit)
    task, planner, checker, authors_checker, warm_s = entry
    entry[4] = 0.0
    dev = torch.device(unit.device)
    c = unit.context
    t = lambda k: None if c.get(k) is None else torch.as_tensor(c[k], dtype=torch.float32)  # noqa: E731
    # an end-effector-goal context carries the dataset's goal configuration for the baselines that need one
    ctx = Context(
        t("q_start"),
        None if task.ee_goal else t("q_goal"),
        t("ee_pos"),
        t("ee_rot"),
        q_goal_ref=t("q_goal") if task.ee_goal else None,
    ).to(dev)
    n = int(unit.params["n_samples"])
    result = planner.plan(ctx, n, unit.plan_seed, record_history=unit.record)
    dense = result.dense
    d64 = _to_cpu64(dense)
    metrics, validity, best = evaluate(
        checker,
        d64,
        q_goal=None if task.ee_goal else ctx.q_goal.cpu().double(),
        ee_goal=None if not task.ee_goal else (ctx.ee_pos.cpu().double(), ctx.ee_rot.cpu().double()),
    )
    row: dict[str, Any] = {
        "cell_key": unit.cell_key,
        "context_index": unit.context_index,
        "plan_seed": unit.plan_seed,
    }
    row.update({k: v for k, v in unit.params.items()})
    row["overrides"] = ",".join(f"{k}={v}" for k, v in sorted(unit.overrides.items()))
    row.update(metrics)
    row["best_index"] = -1 if best is None else best
    theirs = authors_checker.trajectories(d64.q, d64.dq_dt, d64.ddq_dt2).valid
    ours = validity.valid.cpu()
    row["fraction_valid_authors_grid"] = float(theirs.double().mean())
    row["n_flips_valid_to_invalid"] = int((ours & ~theirs).sum())
    row["n_flips_invalid_to_valid"] = int((~ours & theirs).sum())
    row["time_warmup"] = float(warm_s)
    for k, v in result.timings.items():
        if k == "cost_gradient_calls":
            row["n_cost_gradient_calls"] = int(v)
        else:
            row[f"time_{k.replace('/', '_')}"] = float(v)
    for k, v in result.info.items():
        row[f"info_{k}"] = v
    row.update(unit.provenance)
    row["device"] = str(dev) if dev.type != "cuda" else torch.cuda.get_device_name(dev)
    row["finished_at"] = time.time()
    for k, v in list(row.items()):
        if isinstance(v, float) and math.isinf(v):
            row[k] = float("nan")
    hist = None
    if unit.record:
        hist = {
            "q": dense.q.detach().cpu().numpy(),
            "dq": dense.dq_dt.detach().cpu().numpy(),
            "ddq": dense.ddq_dt2.detach().cpu().numpy(),
            "valid": validity.valid.cpu().numpy(),
            "control_points": result.control_points.detach().cpu().numpy(),
        }
        if result.history:
            qs = ctx.q_start
            qg = ctx.q_goal
            steps_q, labels = [], []
            for h in result.history:
                free = h.free.to(dev)
                B = free.shape[0]
                d = planner.param.dense(free, qs.expand(B, -1), None if qg is None else qg.expand(B, -1))
                steps_q.append(d.q.detach().cpu().numpy())
                labels.append(f"{h.label}:{h.step}")
            hist["steps_q"] = np.stack(steps_q)
            hist["steps_valid"] = np.stack(
                [checker.trajectories(torch.as_tensor(q, dtype=torch.float64)).valid.numpy() for q in steps_q]
            )
            hist["steps_label"] = np.array(labels)
    return UnitResult(unit.cell_key, row, hist)


def _to_cpu64(dense):
    from mpd.trajectory import Dense

    return Dense(
        dense.q.detach().cpu().double(),
        dense.dq_ds.detach().cpu().double(),
        dense.ddq_ds2.detach().cpu().double(),
        dense.duration,
    )
