"""``mpd plan``: run one planner on evaluation contexts (or a given start/goal), write trajectories, metrics,
timings and figures."""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from mpd.cli import check_device
from mpd.schema import ConfigError


def _vector(text: str | None, name: str, dof: int) -> np.ndarray | None:
    from mpd.planners.inputs import PlanningInputError, as_array

    if text is None:
        return None
    try:
        v = [float(x) for x in text.replace(" ", "").split(",") if x != ""]
    except ValueError:
        raise ConfigError(f"--{name}", "", f"{text!r} is not a comma-separated list of numbers") from None
    if len(v) != dof:
        raise ConfigError(f"--{name}", "", f"{text!r} has {len(v)} values, the robot has {dof} joints")
    try:
        return as_array(v, f"--{name}", (dof,))
    except PlanningInputError as e:
        raise ConfigError(e.argument, "", e.detail) from None


def _check_configuration(task, q: np.ndarray, name: str, extra_objects: bool, rotation_deg: float) -> None:
    from mpd.collision import CollisionChecker
    from mpd.planners.inputs import PlanningInputError, check_configuration

    try:
        check_configuration(task, q, f"--{name}", CollisionChecker(task, extra_objects, rotation_deg))
    except PlanningInputError as e:
        raise ConfigError(e.argument, "", e.detail) from None


@click.command("plan")
@click.option("--task", "task_name", required=True, help="task name or task file")
@click.option(
    "--planner",
    "planner_name",
    default="mpd",
    show_default=True,
    help="mpd, dprior, dprior-cost, cvae, cvae-cost, gp-cost, rrtconnect-cost",
)
@click.option(
    "--n-samples",
    "--batch",
    "n_samples",
    type=int,
    default=100,
    show_default=True,
    help="trajectories per context",
)
@click.option("--n-contexts", type=int, default=1, show_default=True, help="plan the first N evaluation contexts")
@click.option("--start", default=None, help="start configuration, comma separated (instead of evaluation contexts)")
@click.option(
    "--goal",
    default=None,
    help="goal configuration (joint-goal tasks; for EE-goal tasks its FK is the goal pose)",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--extra-objects", is_flag=True, help="plan with the extra objects (unseen in training)")
@click.option(
    "--rotation",
    type=float,
    default=0.0,
    show_default=True,
    help="rotate the scene about the base z axis (deg)",
)
@click.option("--preset", type=click.Choice(["official", "paper"]), default="official", show_default=True)
@click.option("--sampler", type=click.Choice(["ddim", "ddpm"]), default="ddim", show_default=True)
@click.option(
    "--parametrization",
    type=click.Choice(["bspline", "waypoints"]),
    default=None,
    help="the model's own for a checkpoint path or an identity; bspline for 'latest' and 'default'",
)
@click.option(
    "--model",
    "model_ref",
    default="latest",
    show_default=True,
    help="checkpoint path, model identity (cache or shipped), 'latest' (the newest trained here, else the default "
    "shipped prior) or 'default' (the default shipped prior)",
)
@click.option("--set", "overrides", multiple=True, help="planner setting override, e.g. --set guide_lr=0.5")
@click.option("--device", default=None, callback=check_device)
@click.option("--out", type=click.Path(file_okay=False), required=True, help="output folder")
def plan(
    task_name,
    planner_name,
    n_samples,
    n_contexts,
    start,
    goal,
    seed,
    extra_objects,
    rotation,
    preset,
    sampler,
    parametrization,
    model_ref,
    overrides,
    device,
    out,
):
    """Plan with one method; writes trajectories.npz, metrics.json and figures to OUT."""

    from mpd.collision import CollisionChecker
    from mpd.metrics import evaluate
    from mpd.planners import get_planner_class, make_planner
    from mpd.tasks import load_task

    # -- validate everything before any work ---------------------------------------------------------------
    task = load_task(task_name)
    try:
        cls = get_planner_class(planner_name)
    except ValueError as e:
        raise ConfigError("--planner", "", str(e)) from None
    if n_samples < 1 or n_contexts < 1:
        raise ConfigError("--n-samples/--n-contexts", "", "must be positive")
    from mpd.planners.validation import check_task_settings, parse_assignments

    ov = parse_assignments(overrides, "--set")  # type and range of every setting, before a model is loaded
    if sampler != "ddim":
        ov["sampler"] = sampler
    check_task_settings(task)
    qs, qg = _vector(start, "start", task.dof), _vector(goal, "goal", task.dof)
    if (qs is None) != (qg is None):
        raise ConfigError("--start/--goal", "", "give both a start and a goal, or neither")
    if qs is not None:
        _check_configuration(task, qs, "start", extra_objects, rotation)
        _check_configuration(task, qg, "goal", extra_objects, rotation)
    model = None
    if cls.model_kind is not None:
        model = find_model(task, cls.model_kind, parametrization, model_ref, device=device)
        parametrization = model.parametrization
    parametrization = parametrization or "bspline"
    planner = make_planner(
        planner_name,
        task,
        extra_objects=extra_objects,
        rotation_deg=rotation,
        preset=preset,
        overrides=ov,
        parametrization=parametrization,
        model=model,
        device=device,
    )
    # -- contexts -----------------------------------------------------------------------------------------------
    if qs is not None:
        ctxs = [_context_from_goal(task, qs, qg)]
    else:
        from mpd.data.contexts import evaluation_contexts

        ec = evaluation_contexts(task, max(n_contexts, 1))
        ctxs = [_context_row(task, ec, i) for i in range(n_contexts)]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    checker = CollisionChecker(task, extra_objects, rotation)
    summary, arrays = [], {}
    for i, ctx in enumerate(ctxs):
        res = planner.plan(ctx.to(planner.device), n_samples, seed * 100_003 + i, record_history=(i == 0))
        d = res.dense
        dense64 = type(d)(d.q.cpu().double(), d.dq_ds.cpu().double(), d.ddq_ds2.cpu().double(), d.duration)
        m, val, best = evaluate(
            checker,
            dense64,
            q_goal=None if ctx.q_goal is None else ctx.q_goal.double(),
            ee_goal=None if ctx.ee_pos is None else (ctx.ee_pos.double(), ctx.ee_rot.double()),
        )
        summary.append({"context": i, **m, "best_index": best, "timings": res.timings, "info": res.info})
        arrays[f"ctx{i}_q"] = dense64.q.numpy().astype(np.float32)
        arrays[f"ctx{i}_control_points"] = res.control_points.cpu().numpy()
        arrays[f"ctx{i}_valid"] = val.valid.numpy()
        click.echo(
            f"context {i}: success {m['success']:.0f}  valid {m['fraction_valid']:.2f}  vendi {m['vendi']:.1f}  "
            f"time {res.timings['total']:.3f} s"
        )
        if i == 0:
            _figures(task, planner, ctx, res, val, out, extra_objects, rotation, checker)
    np.savez_compressed(out / "trajectories.npz", **arrays)
    keys = (
        "success",
        "fraction_valid",
        "vendi",
        "ee_pos_error",
        "ee_ori_error_deg",
        "path_length",
        "smoothness",
    )
    mean = {
        k: float(np.nanmean([s[k] for s in summary])) if any(not np.isnan(s[k]) for s in summary) else float("nan")
        for k in keys
    }
    mean["time_total"] = float(np.mean([s["timings"]["total"] for s in summary]))
    doc = {
        "task": task.name,
        "planner": planner_name,
        "preset": preset,
        "n_samples": n_samples,
        "seed": seed,
        "extra_objects": extra_objects,
        "rotation_deg": rotation,
        "model": str(model.path) if model else None,
        "parametrization": parametrization,
        "settings": planner.settings.__dict__,
        "mean": mean,
        "contexts": summary,
    }
    (out / "metrics.json").write_text(json.dumps(doc, indent=2, default=float))
    click.echo("mean: " + "  ".join(f"{k} {v:.3f}" for k, v in mean.items()))
    click.echo(
        f"wrote {out}/trajectories.npz, metrics.json, trajectories.png"
        + (", denoising.png" if (out / "denoising.png").exists() else "")
    )


def find_model(task, kind: str, parametrization: str | None, ref: str, device=None):
    """A trained model: a checkpoint path, a model identity (or its prefix; the cache, then the shipped priors),
    'latest' (the newest of the cache, else the default shipped prior) or 'default' (the default shipped prior)."""
    from mpd.models.find import find_model as find

    try:
        return find(task.name, kind, parametrization, ref, device=device)
    except ConfigError as e:
        raise ConfigError("--model", "", e.detail) from None


def _context_from_goal(task, qs: np.ndarray, qg: np.ndarray):
    import torch

    from mpd.planners import Context

    q_start = torch.as_tensor(qs, dtype=torch.float32)
    q_goal = torch.as_tensor(qg, dtype=torch.float32)
    if task.ee_goal:
        p, r = task.robot.ee_pose(q_goal.double())
        return Context(q_start, None, p.float(), r.float(), q_goal_ref=q_goal)
    return Context(q_start, q_goal)


def _context_row(task, ec, i: int):
    import torch

    from mpd.planners import Context

    f = lambda a: torch.as_tensor(np.asarray(a[i]), dtype=torch.float32)  # noqa: E731
    if task.ee_goal:
        return Context(f(ec.q_start), None, f(ec.ee_pos), f(ec.ee_rot), q_goal_ref=f(ec.q_goal))
    return Context(f(ec.q_start), f(ec.q_goal))


def _figures(task, planner, ctx, res, val, out: Path, extra_objects, rotation, checker) -> None:
    import torch

    from mpd.viz.scene import denoising_figure, trajectory_figure

    env = task.env(extra_objects, rotation)
    d = res.dense
    trajectory_figure(
        task,
        env,
        d.q.cpu().numpy(),
        d.dq_dt.cpu().numpy(),
        d.ddq_dt2.cpu().numpy(),
        val.valid.numpy(),
        out=out / "trajectories.png",
        title=f"{planner.label} - {task.name}",
    )
    if res.history and len(res.history) > 2:
        hist = res.history
        picks = sorted(set(np.linspace(0, len(hist) - 1, 5).round().astype(int)))
        steps = []
        for k in picks:
            h = hist[k]
            B = h.free.shape[0]
            dd = planner.param.dense(
                h.free,
                ctx.q_start.to(h.free).expand(B, -1),
                None if ctx.q_goal is None else ctx.q_goal.to(h.free).expand(B, -1),
            )
            q = dd.q.detach().cpu().double()
            steps.append((f"{h.label} {h.step}", q.numpy(), checker.trajectories(q).valid.numpy()))
        denoising_figure(task, env, steps, out=out / "denoising.png")
    torch.cuda.empty_cache() if torch.cuda.is_available() else None


@click.group("planners")
def planners():
    """List the planners and check a planner (your own too) against the interface."""


@planners.command("list")
def planners_list():
    """The built-in planners and those installed through the `mpd.planners` entry point group."""
    from mpd.planners import get_planner_class, planner_names

    for name in planner_names():
        try:
            cls = get_planner_class(name)
            click.echo(f"{name:18s} {cls.label}  (model: {cls.model_kind or 'none'})")
        except ValueError as e:
            click.echo(f"{name:18s} (broken: {e})")


@planners.command("check")
@click.argument("name")
def planners_check(name):
    """Run the conformance checks on planner NAME (a name, an entry point, or package.module:Class): output shapes,
    boundary conditions, determinism with a seed, timings. Exit 1 with one line on the first failure."""
    from mpd.planners.conformance import PlannerCheckError, check_planner

    try:
        rep = check_planner(name)
    except PlannerCheckError as e:
        raise click.ClickException(str(e)) from None
    for c in rep.checks:
        click.echo(f"ok  {c}")
    click.echo(f"planner {name!r} ({rep.label}) passes the conformance checks")
