"""``mpd tasks``: list the task files, validate one, draw one."""

from __future__ import annotations

from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import TYPE_CHECKING

import click

from mpd.schema import ConfigError

if TYPE_CHECKING:  # torch and the task machinery load inside the verbs, so that `mpd --help` stays fast
    import torch

    from mpd.tasks import Task


def _config_errors(fn: Callable) -> Callable:
    """A bad task file is one line on stderr (file and field) and exit code 2, also when the verb runs in a
    CliRunner or another click program rather than through ``mpd.cli.main``."""

    @wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ConfigError as e:
            click.echo(f"error: {e}", err=True)
            raise SystemExit(2) from None

    return wrapper


def random_valid_configuration(
    task: Task,
    extra_objects: bool = False,
    rotation_deg: float = 0.0,
    seed: int = 0,
    batch: int = 256,
    tries: int = 200,
) -> torch.Tensor:
    """A configuration uniform within the joint limits and collision free (scene and self), seeded."""
    import torch

    from mpd.collision import CollisionChecker

    checker = CollisionChecker(task, extra_objects, rotation_deg)
    g = torch.Generator().manual_seed(seed)
    for _ in range(tries):
        q = task.robot.random_q(batch, g)
        ok = checker.configs(q).valid
        if ok.any():
            return q[int(ok.nonzero()[0, 0])]
    raise RuntimeError(f"{task.name}: no valid configuration in {batch * tries} samples (seed {seed})")


@click.group("tasks")
def tasks() -> None:
    """Task files: the paper's six tasks, or any TOML file with the same layout."""


@tasks.command("list")
@_config_errors
def list_cmd() -> None:
    """Names, robot, context kind and degrees of freedom of the bundled tasks."""
    from mpd.tasks import list_tasks, load_task

    rows = [("task", "robot", "context", "dof")]
    for name in list_tasks():
        t = load_task(name)
        rows.append((t.name, t.robot.name, t.spec.context.kind, str(t.dof)))
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    for r in rows:
        click.echo("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())


@tasks.command("check")
@click.argument("file")
@click.option(
    "--samples", default=100_000, show_default=True, help="random samples per scene for the fractions"
)
@click.option("--seed", default=0, show_default=True)
@_config_errors
def check_cmd(file: str, samples: int, seed: int) -> None:
    """Validate a task file, print a summary and the collision / free-space fractions of both scenes."""
    from mpd.collision import collision_fractions
    from mpd.tasks import load_task

    t = load_task(file)
    s, r = t.spec, t.robot
    env, tr = s.environment, s.trajectory
    lo, hi = (list(v) for v in env.workspace)
    weights = ", ".join(f"{k}={v:g}" for k, v in vars(s.costs.weights).items() if v)
    rows = [
        ("name", t.name),
        ("robot", f"{r.name} ({t.dof} dof, {r.n_spheres} spheres, {len(r.self_pairs)} self-collision pairs)"),
        ("context", s.context.kind),
        ("environment", f"{env.dim}-D, workspace {lo} .. {hi}, SDF cell {env.sdf_cell_size}"),
        ("objects", f"{len(env.obstacles)} obstacles, {len(env.extra_objects)} extra objects"),
        (
            "trajectory",
            f"{tr.duration:g} s, {tr.n_control_points} control points (degree {tr.bspline_degree})",
        ),
        ("costs", weights),
    ]
    click.echo(f"{t.path}: ok")
    for key, text in rows:
        click.echo(f"  {key:12s}{text}")
    point = t.robot.n_spheres == 1 and t.dof == t.dim
    what = "workspace points" if point else "configurations"
    click.echo(f"collision fractions ({samples} random {what} per scene, seed {seed}; free = 1 - value):")
    for key, value in collision_fractions(t, samples, seed).items():
        scene, kind = key.split("/")
        scene = "training scene" if scene == "train" else "extra objects"
        click.echo(f"  {scene:15s} {kind:8s} {value:.4f}")


@tasks.command("show")
@click.argument("task")
@click.option(
    "--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="figure (.png or .pdf)"
)
@click.option("--extra-objects", is_flag=True, help="add the task's extra (unseen) objects")
@click.option(
    "--rotation", "rotation_deg", default=0.0, show_default=True, help="rotate the scene about z [deg]"
)
@click.option("--seed", default=0, show_default=True, help="seed of the random valid configuration")
@_config_errors
def show_cmd(task: str, out: Path, extra_objects: bool, rotation_deg: float, seed: int) -> None:
    """Draw TASK (a name or a .toml file) with the robot at a random valid configuration."""
    from mpd.tasks import load_task
    from mpd.viz.scene import task_figure

    t = load_task(task)
    try:
        q = random_valid_configuration(t, extra_objects, rotation_deg, seed)
    except RuntimeError as e:  # a scene with (almost) no free configuration: say so, no traceback
        raise click.ClickException(str(e)) from None
    task_figure(t, t.env(extra_objects, rotation_deg), q, out=out)
    click.echo(f"wrote {out} (q = {[round(float(v), 4) for v in q]})")
