"""``mpd data``: generate, inspect and draw datasets; measure the validity checkers."""

from __future__ import annotations

import json
from pathlib import Path

import click


@click.group()
def data() -> None:
    """Datasets of collision-free paths (OMPL RRTConnect), defined by datasets/NAME.toml."""


@data.command()
@click.argument("definition")
@click.option("--workers", "-j", type=int, default=None, help="Worker processes (default: all cores).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--executor", type=click.Choice(["local", "ray"]), default="local", show_default=True)
@click.option("--address", default=None, help="Ray cluster address (with --executor ray); default: a local Ray")
def generate(definition: str, workers: int | None, quiet: bool, executor: str, address: str | None) -> None:
    """Generate (or resume) the dataset of DEFINITION (a name under datasets/ or a .toml path); with
    `--executor ray`, every chunk is a Ray task on the cluster (the same chunks, byte for byte)."""
    from mpd.data.generate import generate as run

    lock = run(definition, workers=workers, progress=not quiet, executor=executor, address=address)
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
@click.argument("task_name", required=False)
@click.option("--n", "n", type=int, default=100, show_default=True, help="Contexts of the task's list.")
@click.option(
    "--source",
    type=click.Choice(["held-out", "sampled"]),
    default="held-out",
    show_default=True,
    help="held-out: from the dataset's held-out paths (the default protocol); sampled: dataset-independent.",
)
@click.option("--dataset", default=None, help="Dataset of the held-out contexts (default: <task>-paper, else -small).")
@click.option("--seed", "context_seed", type=int, default=0, show_default=True, help="The context seed.")
@click.option("--extra-objects", is_flag=True, help="The scene with the extra objects (invalid contexts skipped).")
@click.option("--rotation", type=float, default=0.0, show_default=True, help="Scene rotation about z (deg).")
@click.option("--turn", is_flag=True, help="held-out: turn the contexts with a rotated scene (a spec's turn_contexts).")
@click.option("--export", "export", type=click.Path(dir_okay=False), default=None, help="Write the set (.npz or .csv).")
@click.option("--list", "list_files", is_flag=True, help="List the stored context files (of TASK_NAME, if given).")
@click.option("--refresh", is_flag=True, help="sampled: recompute instead of reading the cache.")
def contexts(
    task_name, n, source, dataset, context_seed, extra_objects, rotation, turn, export, list_files, refresh
) -> None:
    """The evaluation contexts of a task in a scene (mpd.data.eval_contexts): build, show, list, export."""
    import numpy as np

    from mpd.data import eval_contexts as ec

    if list_files:
        sets = ec.list_context_files(task_name)
        if not sets:
            click.echo(f"no context files under {ec.contexts_dir()}")
        for cs in sets:
            m = cs.meta
            click.echo(
                f"{cs.hash[:16]}  {cs.task}  {cs.scene}  {len(cs)} contexts ({m.get('n_skipped', 0)} skipped)  "
                f"{m.get('source')}  seed {m.get('context_seed')}  dataset {str(m.get('dataset_hash'))[:12]}  "
                f"{m.get('path')}"
            )
        return
    if not task_name:
        raise click.UsageError("give TASK_NAME (or --list)")
    from mpd.tasks import load_task

    task = load_task(task_name)
    if source == "held-out":
        from mpd.data.dataset import load_dataset
        from mpd.data.generate import default_dataset

        ds = load_dataset(dataset or default_dataset(task.name), generate_missing=False)
        try:
            cs = ec.for_scene(ec.task_contexts(task, ds, n, context_seed), task, extra_objects, rotation, turn=turn)
        except ValueError as e:
            raise click.ClickException(str(e)) from None
    else:
        if refresh:
            from mpd.data.contexts import evaluation_contexts

            evaluation_contexts(task, n, refresh=True)
        cs = ec.sampled_contexts(task, n, extra_objects, rotation)
    d = np.linalg.norm(cs.q_goal - cs.q_start, axis=1)
    click.echo(
        f"{task.name} [{cs.scene}]: {len(cs)} contexts ({cs.meta.get('n_skipped', 0)} of {n} skipped in this scene), "
        f"start-goal distance min {d.min():.3f} mean {d.mean():.3f}"
    )
    click.echo(f"sha256 {cs.hash}")
    click.echo(cs.meta["path"])
    if export:
        out = Path(export)
        if out.suffix == ".csv":
            import pandas as pd

            cols = {"index": cs.index, "dataset_context_id": cs.context_id}
            for k in ("q_start", "q_goal", "ee_pos"):
                a = getattr(cs, k)
                if a is not None:
                    cols.update({f"{k}_{j}": a[:, j] for j in range(a.shape[1])})
            if cs.ee_rot is not None:
                cols.update({f"ee_rot_{j}": cs.ee_rot.reshape(len(cs), 9)[:, j] for j in range(9)})
            pd.DataFrame(cols).to_csv(out, index=False)
        else:
            np.savez(out, **cs.arrays())
        click.echo(f"exported {out}")


@data.command()
@click.argument("name")
@click.option(
    "--root",
    type=click.Path(file_okay=False),
    default=None,
    help="Where to write it (default: the bundled mpd/priors, beside the shipped priors).",
)
def digest(name: str, root: str | None) -> None:
    """Write the digest of a generated dataset NAME: its held-out rows, content hash and control-point range, all an
    evaluation with shipped priors takes from it (then a fresh clone evaluates without generating the dataset)."""
    from mpd.data import digest as dg
    from mpd.data.dataset import load_dataset
    from mpd.experiments.artifacts import data_range
    from mpd.paths import SHIPPED_BUNDLED
    from mpd.tasks import load_task

    try:
        ds = load_dataset(name, generate_missing=False)
    except FileNotFoundError as e:
        raise click.ClickException(str(e)) from None
    task = load_task(ds.task)
    path = dg.write(task, ds, data_range(task, ds), root or SHIPPED_BUNDLED)
    d = dg.load(path)
    click.echo(
        f"{path} ({path.stat().st_size / 1024:.0f} KiB): {len(d)} held-out rows, content {d.info['content_hash'][:16]}"
    )
