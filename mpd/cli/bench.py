"""``mpd bench``: public benchmarks. ``mpd bench mbm import`` reads the MotionBenchMaker Panda problems into the
cache and reports the validity of their starts and goals under mpd's checker; ``mpd bench mbm run`` runs the
RRTConnect baseline on them (resumable) and writes an OMPL benchmark database (Planner Arena); ``mpd bench mbm
prior`` runs a planner with a learned prior (MPD, ...) on the held-out problems; ``mpd bench mbm db`` puts run
folders side by side in one database."""

from __future__ import annotations

from pathlib import Path

import click


def _families(value: str | None) -> tuple[str, ...] | None:
    from mpd.data.mbm import FAMILIES

    if not value:
        return None
    fams = tuple(f.strip() for f in value.split(",") if f.strip())
    bad = [f for f in fams if f not in FAMILIES]
    if bad:
        raise click.BadParameter(f"unknown families {bad} (known: {', '.join(FAMILIES)})", param_hint="--families")
    return fams


def _import(source: Path | None, download: bool, families: tuple[str, ...] | None):
    from mpd.data import mbm
    from mpd.paths import cache_dir

    if download:
        if source is not None:
            raise click.UsageError("--source and --download exclude each other")
        source = mbm.download_sdist(cache_dir() / "mbm" / "sdist")
    return mbm.import_problems(source, families)


def _summary(out_dir: Path, recs: list[dict], families) -> None:
    """Solved problems per family, then the folder's OMPL benchmark database."""
    from mpd.experiments import mbm as mbm_run

    db = mbm_run.write_database(out_dir)
    for fam in families:
        rows = [r for r in recs if r["family"] == fam]
        if rows:
            click.echo(f"{fam:<18} solved {sum(r['success'] for r in rows)}/{len(rows)}")
    click.echo(f"database: {db}")


@click.group()
def bench() -> None:
    """Public benchmarks: the MotionBenchMaker Panda problems (mbm)."""


@bench.group()
def mbm() -> None:
    """MotionBenchMaker (MBM): 7 Panda problem families of 100 problems (docs/MBM.md)."""


_SOURCE = click.option(
    "--source",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="problems.tar.bz2 or a vamp-planner source package (.tar.gz); default: the shipped copy",
)
_DOWNLOAD = click.option("--download", is_flag=True, help="fetch the vamp-planner source package with pip instead")
_FAMILIES = click.option("--families", default=None, help="comma-separated families (default: all seven)")
_GRASP = click.option(
    "--grasp-target",
    type=click.Choice(["obstacle", "ignored"]),
    default="obstacle",
    show_default=True,
    help="the object a goal grasps: an obstacle (strict, as published) or left out of the scene (mpd's hand "
    "covers the gap between its fingers; not comparable with published numbers; docs/MBM.md)",
)
_SLABS = click.option(
    "--cylinder-slabs", type=click.IntRange(1, 64), default=4, show_default=True, help="boxes per cylinder"
)


@mbm.command("import")
@_SOURCE
@_DOWNLOAD
@_FAMILIES
@_SLABS
@_GRASP
@click.option("--no-check", is_flag=True, help="skip the validity of starts and goals")
def import_(source, download, families, cylinder_slabs, grasp_target, no_check) -> None:
    """Read the problems into the cache; per family: problems, starts and goals valid under mpd's checker."""
    from mpd.data import mbm as mbm_data

    fams = _families(families)
    imp = _import(source, download, fams)
    click.echo(f"{imp.root}  (import {imp.identity}, archive sha256 {imp.source_sha256[:16]})")
    header = f"{'family':<18} {'problems':>8}"
    if not no_check:
        header += f" {'start valid':>11} {'goal valid':>10} {'goal hits scene':>15} {'goal beyond limits':>18}"
    click.echo(header)
    for fam in fams or imp.families:
        n = len(imp.problems(fam))
        line = f"{fam:<18} {n:>8}"
        if not no_check:
            v = mbm_data.endpoint_validity(imp, fam, cylinder_slabs, grasp_target)
            line += f" {int(v['start_valid'].sum()):>11} {int(v['goal_valid'].sum()):>10}"
            line += f" {int((~v['goal_env_free']).sum()):>15} {int((~v['goal_within_limits']).sum()):>18}"
        click.echo(line)


@mbm.command("run")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@_SOURCE
@_FAMILIES
@_SLABS
@_GRASP
@click.option("--limit", type=click.IntRange(min=1), default=None, help="the first N problems of each family")
@click.option("--time-limit", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
def run(out_dir, source, families, cylinder_slabs, grasp_target, limit, time_limit, seed) -> None:
    """RRTConnect on the problems, one JSON line each in OUT_DIR/results.jsonl (a rerun resumes), then
    OUT_DIR/benchmark.db (OMPL's benchmark database; open it with plannerarena)."""
    from mpd.experiments import mbm as mbm_run

    fams = _families(families)
    imp = _import(source, False, fams)
    settings = mbm_run.BaselineSettings(
        time_limit=time_limit, seed=seed, cylinder_slabs=cylinder_slabs, grasp_target=grasp_target
    )

    def show(r: dict) -> None:
        t = f"{r['time_first_s']:.3f} s" if r["time_first_s"] is not None else "-"
        click.echo(f"{r['family']}/{r['index']:04d}  {r['status']:<13} first {t}")

    try:
        recs = mbm_run.run_baseline(imp, out_dir, settings, fams, limit, progress=show)
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    _summary(out_dir, recs, fams or imp.families)


@mbm.command("prior")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--method", default="mpd", show_default=True, help="a planner with a model: mpd, dprior, dprior-cost, ..."
)
@click.option("--model", required=True, help="the prior: a model identity (or prefix) or a checkpoint path")
@_FAMILIES
@_SLABS
@click.option(
    "--grasp-target",
    type=click.Choice(["obstacle", "ignored"]),
    default="ignored",
    show_default=True,
    help="the object a goal grasps: an obstacle or left out of the scene (as in datasets/mbm/MBM-RobotPanda-cpu)",
)
@click.option("--first", type=click.IntRange(1, 100), default=51, show_default=True, help="first problem index")
@click.option("--last", type=click.IntRange(1, 100), default=100, show_default=True, help="last problem index")
@click.option("--limit", type=click.IntRange(min=1), default=None, help="the first N of those problems per family")
@click.option("--n-samples", type=click.IntRange(min=1), default=100, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--eager", is_flag=True, help="the eager fp32 network instead of the compiled one")
@click.option("--threads", type=click.IntRange(min=1), default=None, help="torch CPU threads")
def prior(
    out_dir, method, model, families, cylinder_slabs, grasp_target, first, last, limit, n_samples, seed, eager, threads
) -> None:
    """A planner with a learned prior (trained on datasets/mbm/MBM-RobotPanda-cpu: problems 1-50) on the held-out
    problems, each problem's scene given at plan time; one JSON line each in OUT_DIR/results.jsonl (a rerun
    resumes), then OUT_DIR/benchmark.db."""
    import torch

    from mpd import bench as bench_run
    from mpd.experiments import mbm as mbm_run

    if threads:
        torch.set_num_threads(threads)
    fams = _families(families)
    imp = _import(None, False, fams)
    try:
        settings = mbm_run.PriorSettings(
            method=method,
            model=model,
            n_samples=n_samples,
            seed=seed,
            first=first,
            last=last,
            cylinder_slabs=cylinder_slabs,
            grasp_target=grasp_target,
            fast=not eager,
        )
    except ValueError as e:
        raise click.UsageError(str(e)) from None

    def show(r: dict) -> None:
        t = f"{r['time_s']:.3f} s" if r["time_first_s"] is not None else "-"
        fv = f"{r['fraction_valid']:.0%} valid" if r["fraction_valid"] is not None else ""
        click.echo(f"{r['family']}/{r['index']:04d}  {r['status']:<13} {t} {fv}")

    try:
        recs = bench_run.run_prior(imp, out_dir, settings, fams, limit, progress=show)
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    _summary(out_dir, recs, fams or imp.families)


@mbm.command("db")
@click.argument("db_path", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("folders", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--problems", default=None, help="FIRST-LAST: the runs of these problem indices only, e.g. 51-100")
def db(db_path, folders, problems) -> None:
    """One OMPL benchmark database of several run folders (each a planner configuration, e.g. RRTConnect and MPD),
    for Planner Arena."""
    from mpd.experiments import mbm as mbm_run

    span = None
    if problems:
        try:
            span = tuple(int(x) for x in problems.split("-"))
            if len(span) != 2 or not 1 <= span[0] <= span[1] <= 100:
                raise ValueError
        except ValueError:
            msg = f"{problems!r}: expected FIRST-LAST within 1-100"
            raise click.BadParameter(msg, param_hint="--problems") from None
    out = mbm_run.write_database(folders[0], db_path, more=tuple(folders[1:]), problems=span)
    click.echo(f"database: {out}")
