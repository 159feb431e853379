"""Benchmarks run through the Python API (:mod:`mpd.api`): a planner with a learned prior (MPD and the other
diffusion and CVAE planners) on MotionBenchMaker's held-out problems, each problem's scene given at plan time
(``mpd bench mbm prior``). The settings, the records' format, the run folders and the OMPL benchmark database are
:mod:`mpd.experiments.mbm`'s, shared with the RRTConnect baseline."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from mpd.data.mbm import FAMILIES, Imported, grasp_points, grasped_object
from mpd.experiments.mbm import PRIOR_TASK, PriorSettings, append_results, read_results, settings_file


def load_prior_planner(settings: PriorSettings):
    """The planner of ``settings`` on :data:`PRIOR_TASK`, warmed up."""
    from mpd.api import load_planner

    planner = load_planner(
        PRIOR_TASK, settings.method, model=settings.model or None, fast=settings.fast, sdf_mode=settings.sdf_mode
    )
    planner.warmup(settings.n_samples)
    return planner


def run_prior_problem(planner, family: str, problem, settings: PriorSettings) -> dict:
    """One problem with a learned prior's planner (:func:`load_prior_planner`); the record of :data:`RESULTS`.
    ``success``: some trajectory of the batch is valid under mpd's checker in the problem's scene (the goal reached:
    the B-spline ends on it); ``time_s``: the plan itself (``timings["total"]``: the scene's grid, the warm-up and the
    final check are not in it); path length and smoothness of the shortest valid trajectory."""
    from mpd.api import Box, PlanningInputError, Sphere
    from mpd.data.planning import problem_seed

    task = planner.task
    left_out = None
    if settings.grasp_target == "ignored":
        left_out = grasped_object(problem, grasp_points(task.robot, [problem.goal])[0])
    boxes = [
        Sphere(p.centre, p.radius) if p.kind == "sphere" else Box(p.centre, p.half_size, rotation=p.rotation)
        for p in problem.primitives(settings.cylinder_slabs, without=left_out)
    ]
    seed = problem_seed("mbm", settings.seed, problem.name)
    rec = {
        "family": family,
        "index": problem.index,
        "seed": seed,
        "left_out": left_out,
        "success": False,
        "status": None,
        "time_first_s": None,
        "time_s": 0.0,
        "scene_s": None,
        "n_samples": settings.n_samples,
        "fraction_valid": None,
        "path_length": None,
        "smoothness": None,
        "valid_mpd": None,
    }
    try:
        plan = planner.plan(problem.start, problem.goal, obstacles=boxes, n_samples=settings.n_samples, seed=seed)
    except PlanningInputError as e:
        # an invalid start or goal (in the scene or beyond mpd's joint limits) is refused before planning
        rec["status"] = "invalid_start" if e.argument == "q_start" else "invalid_goal"
        rec["error"] = str(e)
        return rec
    m = plan.metrics
    ok = bool(plan.valid.any())
    rec.update(
        success=ok,
        status="ok" if ok else "no_valid",
        time_first_s=float(plan.timings["total"]),
        time_s=float(plan.timings["total"]),
        scene_s=float(plan.timings["scene"]),
        fraction_valid=float(plan.valid.mean()),
        path_length=float(m["best_path_length"]) if ok else None,
        smoothness=float(m["best_smoothness"]) if ok else None,
        valid_mpd=ok,
    )
    return rec


def run_prior(
    imported: Imported,
    out_dir: str | Path,
    settings: PriorSettings,
    families: tuple[str, ...] | None = None,
    limit: int | None = None,
    progress=None,
) -> list[dict]:
    """A learned prior's planner on problems ``settings.first``..``settings.last`` of ``families`` (the first
    ``limit`` of them), appending to ``out_dir/results.jsonl`` and skipping the problems already there."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fams = tuple(FAMILIES if families is None else families)
    todo = []
    for fam in fams:
        kept = [p for p in imported.problems(fam) if settings.first <= p.index <= settings.last]
        todo += [(fam, p) for p in kept[:limit]]
    done = {(r["family"], r["index"]) for r in read_results(out)}
    todo = [(f, p) for f, p in todo if (f, p.index) not in done]
    meta = {
        "baseline": "prior",
        "settings": asdict(settings),
        "mbm_identity": imported.identity,
        "task": PRIOR_TASK.name,
    }
    written = (out / "settings.json").is_file()
    if written:
        settings_file(out, meta, PriorSettings)  # other settings fail here, before the planner's ~30 s set-up
    planner = load_prior_planner(settings) if todo else None
    if not written:
        identity = None if planner is None or planner.model is None else planner.model.meta.get("identity")
        if identity is not None:
            meta["model_identity"] = identity
        settings_file(out, meta, PriorSettings)
    return append_results(out, todo, lambda fam, p: run_prior_problem(planner, fam, p, settings), progress)
