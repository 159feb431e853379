"""``mpd data``: generate, inspect and draw datasets; measure the validity checkers."""

from __future__ import annotations

import json

import click


@click.group()
def data() -> None:
    """Datasets of collision-free paths (OMPL RRTConnect), defined by datasets/NAME.toml."""


@data.command()
@click.argument("definition")
@click.option("--workers", "-j", type=int, default=None, help="Worker processes (default: all cores).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def generate(definition: str, workers: int | None, quiet: bool) -> None:
    """Generate (or resume) the dataset of DEFINITION (a name under datasets/ or a .toml path)."""
    from mpd.data.generate import generate as run

    lock = run(definition, workers=workers, progress=not quiet)
    if not lock:
        raise click.ClickException("generation did not complete")
    f = lock["figures"]
    click.echo(
        f"{lock['name']}: {f['successes']}/{f['contexts']} contexts planned, {f['paths']} paths "
        f"(with reversed copies), fit collision free {f['fit_collision_free_rate']}, "
        f"{f['paths_per_s_per_core']} paths/s per core"
    )
    click.echo(f"identity {lock['identity']}, content {lock['content_hash'][:16]}")


@data.command()
@click.argument("name")
@click.option("--json", "as_json", is_flag=True, help="Print the lock record as JSON.")
def info(name: str, as_json: bool) -> None:
    """Counts, hashes and generation figures of dataset NAME."""
    from mpd.data.definition import load_definition
    from mpd.data.generate import chunk_states

    rd = load_definition(name)
    bad = chunk_states(rd)
    try:
        lock = json.loads(rd.lock_path.read_text())
    except FileNotFoundError:
        lock = {}
    d = rd.definition
    if as_json:
        click.echo(json.dumps(lock | {"unusable_chunks": {str(k): v for k, v in bad.items()}}, indent=1))
        return
    click.echo(f"{rd.name}  task {d.task}  contexts {d.n_contexts}  seed {d.seed}")
    click.echo(f"identity {rd.identity}  data {rd.data_dir}")
    done = d.n_chunks - len(bad)
    click.echo(
        f"chunks {done}/{d.n_chunks} complete and verified"
        + (f"; unusable: {dict(sorted(bad.items()))}" if bad and len(bad) < 10 else "")
    )
    if lock.get("identity") != rd.identity:
        click.echo("lock file: " + ("missing" if not lock else f"stale (identity {lock.get('identity')})"))
        return
    click.echo(f"content hash {lock['content_hash']}")
    for k, v in lock["figures"].items():
        click.echo(f"  {k}: {v}")


@data.command()
@click.argument("name")
@click.option("--out", "-o", required=True, type=click.Path(dir_okay=False), help="Output image (.png, .pdf).")
@click.option("--n", "n_paths", type=int, default=50, show_default=True, help="Paths drawn.")
@click.option("--split", type=click.Choice(["train", "val", "test", "all"]), default="all", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Which random sample of paths.")
def show(name: str, out: str, n_paths: int, split: str, seed: int) -> None:
    """Draw a sample of the paths of dataset NAME over the environment (the paper's Fig. 5 style)."""
    import numpy as np

    from mpd.data.dataset import load_dataset
    from mpd.tasks import load_task

    ds = load_dataset(name, generate_missing=False)
    if split != "all":
        ds = ds.subset(split)
    task = load_task(ds.task)
    pick = np.random.default_rng(seed).permutation(len(ds))[:n_paths]
    paths = ds.paths[pick].astype(np.float64)
    try:
        from mpd.viz.scene import draw_paths_figure
    except ImportError:
        draw_paths_figure = None
    title = f"{ds.name}: {len(pick)} of {len(ds)} paths ({split})"
    if draw_paths_figure is not None:
        goal = ds.ee_pos[pick] if ds.ee_pos is not None else None
        draw_paths_figure(
            task,
            task.env(),
            paths,
            valid=ds.fit_free[pick],
            out=out,
            title=title,
            max_paths=n_paths,
            goal_pos=goal,
        )
    else:
        _simple_figure(task, paths, out, title)
    click.echo(out)


def _simple_figure(task, paths, out: str, title: str) -> None:
    """Fallback drawing (end-effector paths over the obstacles) when mpd.viz.scene is not available."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    ee = task.robot.ee_pose(torch.as_tensor(paths))[0].numpy()
    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(111, projection="3d" if task.dim == 3 else None)
    for prim, _extra in task.env().primitives:
        if task.dim == 2 and prim.kind == "sphere":
            ax.add_patch(plt.Circle(prim.centre, prim.radius, color="0.5"))
    for p in ee:
        ax.plot(*p[:, : task.dim].T, lw=0.8, alpha=0.7)
    ax.set_title(title, fontsize=8)
    fig.savefig(out, dpi=150)
    plt.close(fig)


@data.command()
@click.argument("task_name")
@click.option("--n", "n", type=int, default=10_000, show_default=True, help="Random configurations.")
def measure(task_name: str, n: int) -> None:
    """Sphere model vs PyBullet meshes on random configurations, and the speed of each checker."""
    from mpd.data.measure import checker_speeds, planning_speed, sphere_vs_mesh
    from mpd.tasks import load_task

    task = load_task(task_name)
    for k, v in sphere_vs_mesh(task, n).items():
        click.echo(f"{k}: " + ", ".join(f"{a} {b:.4f}" for a, b in v.items()))
    for k, v in checker_speeds(task).items():
        click.echo(f"{k}: {v:.4g}")
    for k, v in planning_speed(task).items():
        click.echo(f"planning with {k}: " + ", ".join(f"{a} {b:.4g}" for a, b in v.items()))


@data.command()
@click.argument("task_name")
@click.option("--n", "n", type=int, default=100, show_default=True)
@click.option("--refresh", is_flag=True, help="Recompute instead of reading the cache.")
def contexts(task_name: str, n: int, refresh: bool) -> None:
    """Compute (or show) the fixed evaluation contexts of a task."""
    import numpy as np

    from mpd.data.contexts import contexts_cache_path, evaluation_contexts
    from mpd.tasks import load_task

    task = load_task(task_name)
    c = evaluation_contexts(task, n, refresh=refresh)
    d = np.linalg.norm(c.q_goal - c.q_start, axis=1)
    click.echo(f"{task.name}: {len(c)} contexts, start-goal distance min {d.min():.3f} mean {d.mean():.3f}")
    click.echo(str(contexts_cache_path(task, n)))
