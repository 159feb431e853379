"""``mpd train`` and ``mpd models list``."""

from __future__ import annotations

import json
from pathlib import Path

import click

from mpd.cli import check_device


@click.command("train")
@click.option("--task", "task_name", required=True, help="task name or task file")
@click.option("--model", "kind", type=click.Choice(["diffusion", "cvae"]), default="diffusion", show_default=True)
@click.option("--parametrization", type=click.Choice(["bspline", "waypoints"]), default="bspline", show_default=True)
@click.option("--profile", default="cpu", show_default=True, help="training profile of the task file: cpu or paper")
@click.option(
    "--dataset",
    default=None,
    help="dataset name or definition file (default: <task>-paper if generated, else <task>-small)",
)
@click.option("--steps", type=click.IntRange(min=1), default=None, help="override the profile's number of steps")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--device", default=None, callback=check_device, help="cpu, cuda, ... (default: CUDA when present)")
@click.option(
    "--threads", type=click.IntRange(min=1), default=None, help="torch CPU threads (1 is fastest on a busy machine)"
)
@click.option("--mlflow", is_flag=True, help="also log the training to the local MLflow store (mlflow extra)")
@click.option(
    "--no-shipped",
    is_flag=True,
    help="train even when a shipped prior of this identity exists (reproduces it; the cache copy is then retrained)",
)
@click.option(
    "--from",
    "start_from",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="start from this checkpoint of a longer or shorter budget of the same training (a last.pt or a copy of one; "
    "constant or wsd schedule, a step both budgets pass through) instead of step 0",
)
@click.option(
    "--data-parallel",
    "data_parallel",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="train on this many processes, each on a slice of every batch (a diffusion prior on a CPU; with 2 on an "
    "idle 2-core CPU and --threads 1, 1.3-1.6x faster in wall-clock time; the same model, up to float rounding)",
)
@click.option(
    "--init-from",
    "init_from",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="start from this checkpoint's EMA weights (a model.pt, a shipped prior, a last.pt; the same task data and "
    "network) with a fresh optimizer instead of the seed's initialization: another model, whose identity says so",
)
def train(
    task_name, kind, parametrization, profile, dataset, steps, seed, device, threads, mlflow, no_shipped, start_from,
    data_parallel, init_from,
):  # fmt: skip
    """Train (or find, when this exact model exists in the cache or among the shipped priors) a prior; prints the
    checkpoint path."""
    import dataclasses

    import torch

    from mpd.data.dataset import load_dataset
    from mpd.models.data import training_arrays
    from mpd.models.train import train_model
    from mpd.tasks import load_task

    if threads:
        torch.set_num_threads(threads)
    task = load_task(task_name)
    spec = task.training(profile)
    if steps is not None:
        spec = dataclasses.replace(
            spec, steps=steps, val_every=min(spec.val_every, steps), checkpoint_every=min(spec.checkpoint_every, steps)
        )
    from mpd.data.generate import default_dataset

    name = dataset or default_dataset(task.name)
    click.echo(f"dataset {name}")
    ds = load_dataset(name)
    arrays = training_arrays(task, ds, parametrization)
    del ds  # the training arrays hold what training needs; a paper-size dataset's control points are ~2 GB
    path = train_model(
        arrays, kind, task.model(profile), spec, seed=seed, device=device, shipped=not no_shipped,
        start_from=start_from, data_parallel=data_parallel, init_from=init_from,
    )  # fmt: skip
    click.echo(f"model: {path}")
    if mlflow:
        from mpd.experiments.tracking import log_model_to_mlflow

        log_model_to_mlflow(Path(path).parent / "meta.json")


@click.group("models")
def models():
    """Trained models in the cache."""


@models.command("list")
@click.option("--task", "task_name", default=None)
def models_list(task_name):
    import pandas as pd

    from mpd.models.train import list_models

    rows = []
    for m in list_models(task_name):
        rows.append(
            {
                "task": m.get("task_name"),
                "kind": m.get("kind"),
                "parametrization": m.get("parametrization"),
                "identity": m.get("identity"),
                "steps": (m.get("training_spec") or {}).get("steps"),
                "val_loss": m.get("final_val_loss"),
                "steps/s": m.get("steps_per_s"),
                "dataset": str(m.get("dataset_hash", ""))[:12],
                "path": m.get("path"),
            }
        )
    if not rows:
        click.echo("no trained models yet (mpd train --task NAME)")
        return
    with pd.option_context("display.width", 250, "display.max_colwidth", 120):
        click.echo(pd.DataFrame(rows).to_string(index=False))


@models.command("ship")
@click.argument("model_path", type=click.Path(exists=True))
@click.option("--root", default=None, help="folder of shipped priors (default: the package's mpd/priors)")
@click.option(
    "--dtype",
    "weights_dtype",
    type=click.Choice(["auto", "float32", "bfloat16"]),
    default="auto",
    show_default=True,
    help="weights as stored (auto: float32 if within the 10 MB limit, else bfloat16)",
)
def models_ship(model_path, root, weights_dtype):
    """Write a trained model (a cache model.pt or its folder) as a shipped prior with its lock file."""
    from mpd.models import shipped

    try:
        path = shipped.ship(model_path, root or shipped.BUNDLED, weights_dtype=weights_dtype)
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    lock = json.loads(path.with_name(path.name[: -len(".pt")] + ".lock.json").read_text())
    click.echo(f"shipped: {path} ({path.stat().st_size / 2**20:.2f} MB, {lock['weights_dtype']} weights)")


@models.command("shipped")
def models_shipped():
    """The shipped priors, each verified against its lock file (exit code 1 when one does not verify)."""
    from mpd.models import shipped

    rows = shipped.list_shipped()
    if not rows:
        click.echo("no shipped priors")
        return
    bad = 0
    for r in rows:
        state = "ok" if r["ok"] else f"CORRUPTED: {r['problem']}"
        bad += not r["ok"]
        steps = r.get("steps")
        click.echo(f"{r.get('task_name', '?')}  {Path(r['path']).name}  steps={steps}  {state}")
    if bad:
        raise SystemExit(1)
