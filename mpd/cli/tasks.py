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
@click.option("--samples", default=100_000, show_default=True, help="random samples per scene for the fractions")
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
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="figure (.png or .pdf)")
@click.option("--extra-objects", is_flag=True, help="add the task's extra (unseen) objects")
@click.option("--rotation", "rotation_deg", default=0.0, show_default=True, help="rotate the scene about z [deg]")
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


_TASK_HEADER = """\
# {name}: a task of your own, written by `mpd tasks new {name} --like {base}` (a copy of {base}).
# What to edit (every field: docs/OWN_TASK.md and the bundled tasks in mpd/tasks/data/):
#   [environment]        workspace, obstacles ([[environment.obstacles]]: type "sphere" with centre and radius, or
#                        "box" with centre and size) and the extra objects of the unseen scene
#   [robot].name         the robot (RobotPointMass2D, RobotPlanar2Link, RobotPlanar4Link, RobotPanda)
#   [trajectory]         duration, control points; [costs.weights]; [training.<profile>] (steps, batch size);
#                        [model] the network's sizes, [model_profiles.<profile>] a profile's changes to them
# Check it:  mpd tasks check {file}     Draw it:  mpd tasks show {file} --out {name}.png
# The name below is the task's identity in every result, figure and recording: keep it unique.
"""

_DATA_TEMPLATE = """\
# {data}: the training data of {name}, written by `mpd tasks new` (RRTConnect paths in the training scene,
# fitted with B-splines). Generate it: mpd data generate {data_file}   (`mpd run` generates it when missing).
# Every field: datasets/README.md; fields left out take the task's values.
name = "{data}"
task = "{file}"  # a path relative to this file, or a bundled task's name
description = "training paths of {name}"
n_contexts = {n_contexts}  # start/goal problems; 10000 for a paper-size dataset
seed = 0
chunk_size = {chunk}

[checker]
kind = "spheres"

[split]
# held-out shares of the contexts (the rest trains the models); the evaluation contexts are the held-out ones at
# least the task's [context].min_start_goal_distance apart (`mpd data contexts`), so keep enough of them
val = 0.1
test = 0.2
"""


@tasks.command("new")
@click.argument("name")
@click.option("--like", "base", default="EnvSimple2D-RobotPointMass2D", show_default=True, help="task to copy")
@click.option(
    "--out",
    "out_dir",
    default=".",
    show_default=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="folder of the new files",
)
@click.option("--n-contexts", default=500, show_default=True, type=click.IntRange(min=1), help="dataset size")
@click.option("--force", is_flag=True, help="overwrite existing files")
@_config_errors
def new_cmd(name: str, base: str, out_dir: Path, n_contexts: int, force: bool) -> None:
    """Write a commented task file NAME.toml (a copy of --like) and its dataset definition NAME-data.toml."""
    import tomllib

    from mpd.schema import from_dict
    from mpd.tasks import load_task
    from mpd.tasks.spec import TaskSpec

    src = load_task(base)
    task_file, data_file = out_dir / f"{name}.toml", out_dir / f"{name}-data.toml"
    for f in (task_file, data_file):
        if f.exists() and not force:
            raise ConfigError(f, "", "exists already (--force overwrites it)")
    lines = src.path.read_text().splitlines(keepends=True)
    body = lines[next(i for i, line in enumerate(lines) if not line.startswith("#")) :]  # the base's header out
    text = "".join(body)
    old = f'name = "{src.name}"'
    if old not in text:
        raise ConfigError(src.path, "name", f"expected a line {old!r} to rename")
    text = _TASK_HEADER.format(name=name, base=src.name, file=task_file.name) + text.replace(old, f'name = "{name}"', 1)
    if f'description = "{src.spec.description}"' in text:
        text = text.replace(f'description = "{src.spec.description}"', f'description = "{name} (from {src.name})"')
    from_dict(TaskSpec, tomllib.loads(text), source=task_file)  # e.g. the new name must be a valid one
    data = _DATA_TEMPLATE.format(
        data=f"{name}-data",
        name=name,
        file=task_file.name,
        data_file=data_file.name,
        n_contexts=n_contexts,
        chunk=max(1, min(50, n_contexts)),
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    task_file.write_text(text)
    data_file.write_text(data)
    click.echo(f"wrote {task_file} (a copy of {src.name}) and {data_file}")
    click.echo(f"next: mpd tasks check {task_file}  and  mpd data generate {data_file}")
