"""``mpd run SPEC`` and ``mpd runs list|show|compare``."""

from __future__ import annotations

import ast
import sys

import click

from mpd.cli import check_device
from mpd.schema import ConfigError


def _parse_only(items: tuple[str, ...], source: str) -> dict[str, list]:
    out: dict[str, list] = {}
    for it in items:
        if "=" not in it:
            raise ConfigError(source, "--only", f"expected KEY=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        vals = []
        for part in v.split(","):
            try:
                val = ast.literal_eval(part)
            except (ValueError, SyntaxError):
                val = {"true": True, "false": False}.get(part.lower(), part)
            vals.append(val)
        out.setdefault(k.strip(), []).extend(vals)
    return out


@click.command("run")
@click.argument("spec")
@click.option("--only", multiple=True, help="keep only cells with KEY=VALUE (repeatable; VALUE may be a,b,c)")
@click.option("--executor", type=click.Choice(["local", "ray"]), default="local", show_default=True)
@click.option("--address", default=None, help="Ray cluster address (with --executor ray); default: a local Ray")
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="parallel processes (local) or CPUs (local Ray)",
)
@click.option("--dry-run", is_flag=True, help="print the cells, what would be generated or trained, and the work")
@click.option("--fresh", is_flag=True, help="discard this spec's previous results at this commit and start over")
@click.option(
    "--run-dir",
    type=click.Path(),
    default=None,
    help="where the run lives (default: runs/<spec>-<hash>-<commit>)",
)
@click.option(
    "--device", default=None, callback=check_device, help="cpu, cuda, cuda:1 ... (default: CUDA when present)"
)
@click.option("--report/--no-report", default=False, help="write the report and the Rerun recording at the end")
@click.option("--mlflow", is_flag=True, help="also log the run to the local MLflow store (needs the mlflow extra)")
@click.option(
    "--keep-going", is_flag=True, help="with --report: exit 0 even when a figure cannot be drawn (it is listed)"
)
@click.option(
    "--threads",
    type=click.IntRange(min=1),
    default=None,
    help="torch threads of the planning process with --workers 1 (worker processes always use 1); set it on a busy "
    "machine: more threads than free cores makes OpenMP spin and can be 10x slower",
)
@click.option(
    "--scale",
    type=click.FloatRange(min=0, min_open=True, max=1),
    default=None,
    help="shrink every cell by this factor (contexts, samples, training steps, dataset size; with floors): the "
    "whole spec end to end in minutes, e.g. to try a cluster before the real run; a run and artifacts of its own",
)
def run(
    spec, only, executor, address, workers, dry_run, fresh, run_dir, device, report, mlflow, keep_going, threads, scale
):
    """Run an experiment SPEC (a name under benchmarks/specs/ or a path)."""
    from mpd.experiments.runner import Runner
    from mpd.experiments.spec import load_spec, scale_spec

    s = load_spec(spec)
    if scale is not None:
        s = scale_spec(s, scale)
    only_d = _parse_only(only, str(s.path))
    from mpd.experiments.spec import AXES, MODEL_PREFIX, PLANNER_PREFIX, TRAINING_PREFIX

    for k in only_d:
        if k not in AXES and not k.startswith((PLANNER_PREFIX, TRAINING_PREFIX, MODEL_PREFIX)):
            raise ConfigError(
                "--only",
                k,
                f"unknown axis (allowed: {', '.join(AXES)}, planner.<setting>, training.<field>, model.<field>)",
            )
    if "task" in only_d:  # a task given by its path selects the cells of its name
        only_d["task"] = [s.task_name(str(t)) for t in only_d["task"]]
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    from mpd.viz.recording import stream_unit

    runner = Runner(
        s, only_d or None, executor, workers, address, run_dir, fresh, device, mlflow=mlflow, recorder=stream_unit
    )
    if not runner.cells:
        raise ConfigError(s.path, "--only", "no cell matches")
    if dry_run:
        click.echo(runner.describe())
        return
    out = runner.run()
    click.echo(f"results: {out / 'results.parquet'}")
    if report:
        from mpd.viz.report import FigureError, build_report

        try:
            rep = build_report(out, keep_going=keep_going)
        except FigureError as e:
            raise click.ClickException(f"report {out / 'report' / 'index.md'}: {e} (--keep-going: exit 0)") from None
        click.echo(f"report: {rep}")
        recs = sorted((out / "recordings").glob("*.rrd")) if (out / "recordings").exists() else []
        if recs:
            # the highlight first: MPD with the extra objects, the paper's point
            recs.sort(key=lambda p: (("-mpd-extra" not in p.name), ("-mpd-" not in p.name), p.name))
            click.echo(
                f"recording: {recs[0]}" + (f" (+{len(recs) - 1} more in {recs[0].parent})" if len(recs) > 1 else "")
            )
            click.echo(f"open the recording: nox -s view -- {out.name}   (or: mpd view {out.name} --web)")
        else:
            click.echo("no recordings (record_contexts = 0)")


@click.group("runs")
def runs():
    """List, show and compare runs."""


@runs.command("list")
def runs_list():
    from mpd.experiments.tracking import list_runs

    df = list_runs()
    click.echo("no runs yet" if df.empty else df.to_string(index=False))


@runs.command("show")
@click.argument("run", default="latest")
def runs_show(run):
    from mpd.experiments.runner import resolve_run
    from mpd.experiments.tracking import show_run

    click.echo(show_run(resolve_run(run)))


@runs.command("compare")
@click.argument("run_a")
@click.argument("run_b")
@click.option("--tol", type=float, default=0.0, show_default=True, help="ignore differences up to this size")
@click.option(
    "--equivalent",
    is_flag=True,
    help="assert that B reproduces A: exit 1 unless every cell is bit-identical or equivalent within noise and "
    "no task file or dataset changed",
)
def runs_compare(run_a, run_b, tol, equivalent):
    """Per-cell metric differences B - A, flagging cells whose inputs (task, dataset, model) changed, then per
    cell and metric whether B differs from A beyond noise (paired permutation tests over contexts, false-discovery
    rate 5 %)."""
    import pandas as pd

    from mpd.experiments.reproduce import compare, format_comparison
    from mpd.experiments.runner import resolve_run
    from mpd.experiments.tracking import compare_runs

    a, b = resolve_run(run_a), resolve_run(run_b)
    table, notes = compare_runs(a, b, tol)
    with pd.option_context("display.width", 220, "display.max_columns", 30, "display.max_rows", 500):
        click.echo(table.to_string(index=False, float_format=lambda x: f"{x:+.4f}"))
    for n in notes:
        click.echo(n)
    result = compare(a, b, tol)
    click.echo("")
    click.echo(format_comparison(result))
    if equivalent:
        if result.equivalent:
            click.echo(f"equivalent: {b.name} reproduces {a.name}")
        else:
            click.echo(f"not equivalent: {'; '.join(result.failures)}", err=True)
            sys.exit(1)
    sys.exit(0)
