"""A run's report: ``run_dir/report/`` with figures (PNG; PDF too on demand), Markdown tables and ``index.md``.

Everything comes from the results table (``mpd.experiments.results.read_results``), the manifest and, for the
scene figures and the Rerun recordings, the recorded histories. Rebuilding it from the same table gives the same
Markdown: nothing in it depends on when or where it was built.

    report/
      index.md            one page: provenance, figures, tables, recordings
      summary.md          mean [95 % interval] over contexts per task x scene x method, interquartile means, and
                          how many contexts a claim needs
      paired.md           MPD against each baseline on the same contexts (mean difference, P(MPD better))
      reproducibility.md  every cell against a reference run: bit-identical, equivalent, differs, and why
      paper.md            the paper's stated numbers beside ours
      timing.md           time per cell, per cost
      figures/<name>.png  (and .pdf with formats=("png", "pdf"): `mpd report RUN --pdf`)
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mpd.experiments.results import read_results
from mpd.viz.report_data import EXTRA, TRAIN, method_label, method_order, prepare, short_task, task_order
from mpd.viz.report_figures import FIGURES, add_caption, ee_goal
from mpd.viz.report_stats import (
    AUTHORS_GRID_NOTE,
    PAIRED_NOTE,
    authors_grid_table,
    contexts_summary,
    contexts_table,
    default_reference,
    iqm_table,
    paired_table,
    reproducibility,
)
from mpd.viz.report_tables import markdown_table, paper_table, summary_table, timing_table
from mpd.viz.report_training import TRAINING_NOTE, has_curves, recipes_table

log = logging.getLogger(__name__)

SUMMARY_NOTE = (
    "Mean [95 % interval] over contexts: a bootstrap over the cell's contexts (2000 resamples, seeded), Wilson's "
    "interval for success (0 or 1 per context)."
)
IQM_NOTE = (
    "Interquartile mean (the mean of the middle 50 % of contexts) [95 % bootstrap interval], for the metrics whose "
    "distribution over contexts is skewed: a few failed contexts pull the mean, not the IQM."
)


@dataclass
class Entry:
    """One figure of the report: its file stem, title, and why it is missing (None when written)."""

    name: str
    title: str
    skipped: str | None = None


# --------------------------------------------------------------------------------------------- provenance
def _manifest(run_dir: Path) -> dict:
    p = run_dir / "manifest.json"
    return json.loads(p.read_text()) if p.exists() else {}


def _first(df: pd.DataFrame, col: str, default=""):
    if col in df.columns and df[col].notna().any():
        return df[col].dropna().iloc[0]
    return default


def run_info(run_dir: Path, man: dict, df: pd.DataFrame) -> dict:
    """Spec, hash, commit: from the manifest, else from the table's provenance columns."""
    prov = man.get("provenance", {})
    commit = prov.get("git_commit") or str(_first(df, "git_commit", "unknown"))
    dirty = prov.get("git_dirty", bool(_first(df, "git_dirty", False)))
    return {
        "run_id": man.get("run_id") or str(_first(df, "run_id", run_dir.name)),
        "spec": man.get("spec_name") or str(_first(df, "spec_name", "?")),
        "spec_hash": man.get("spec_hash") or str(_first(df, "spec_hash", "?")),
        "commit": commit,
        "dirty": bool(dirty),
    }


def caption(info: dict) -> str:
    return (
        f"spec {info['spec']} ({info['spec_hash']}) · commit {info['commit'][:10]}"
        f"{' (dirty)' if info['dirty'] else ''} · run {info['run_id']}"
    )


def _provenance_md(run_dir: Path, man: dict, df: pd.DataFrame, info: dict) -> list[str]:
    prov = man.get("provenance", {})
    rows = [
        ["run", f"`{info['run_id']}`"],
        ["spec", f"{info['spec']} (`{man.get('spec_path', '?')}`)"],
        ["spec hash", f"`{info['spec_hash']}`"],
        ["commit", f"`{info['commit']}`" + (" (dirty working tree)" if info["dirty"] else "")],
        ["status", str(man.get("status", "?"))],
        ["device", ", ".join(sorted({str(v) for v in df["device"].dropna()})) if "device" in df else "?"],
        ["executor", f"{man.get('executor', '?')}, workers: {man.get('workers', '?')}"],
        ["rows (cell × context)", str(len(df))],
        ["cells", str(df["cell_key"].nunique() if "cell_key" in df else "?")],
    ]
    for key, label in (("started_at", "started"), ("finished_at", "finished")):
        if man.get(key):
            rows.append([label, pd.Timestamp(man[key], unit="s", tz="UTC").strftime("%Y-%m-%d %H:%M:%S UTC")])
    out = ["## Provenance", "", markdown_table(["", ""], rows), ""]
    # inputs per task: the manifest's artifacts, completed by the table's hashes (a run may be a merge)
    arts = man.get("artifacts", {}) or {}
    trows = []
    for task in task_order(df["task"].unique()):
        g = df[df["task"] == task]
        a = arts.get(task, {})
        hashes = (
            lambda c, g=g: (
                (  # noqa: E731
                    ", ".join(sorted({f"`{str(v)[:16]}`" for v in g[c].dropna() if str(v)})) if c in g else ""
                )
                or "–"
            )
        )
        models = a.get("models") or {}
        model_ids = ", ".join(f"{k} `{v}`" for k, v in sorted(models.items())) if models else "–"
        trows.append(
            [
                task,
                f"`{str(a.get('task_hash', _first(g, 'task_hash')))[:16]}`",
                f"{a.get('dataset_id', _first(g, 'dataset_id', '–'))} ({hashes('dataset_hash')})",
                model_ids,
                hashes("model_hash"),
            ]
        )
    out += [
        "### Inputs per task",
        "",
        markdown_table(["task", "task file", "dataset (content hash)", "models", "model file hashes"], trows),
        "",
    ]
    crows = []
    for task in task_order(df["task"].unique()):
        for scene, c in sorted((arts.get(task, {}).get("contexts") or {}).items()):
            crows.append(
                [
                    task,
                    scene,
                    str(c.get("source", "")),
                    str(c.get("n_contexts", "")),
                    str(c.get("n_skipped", 0)),
                    str(c.get("context_seed", "")),
                    f"`{str(c.get('sha256', ''))[:16]}`",
                ]
            )
    if crows:
        out += [
            "### Evaluation contexts",
            "",
            "One content-addressed file per task and scene (`mpd data contexts --list`): held-out contexts of the "
            "dataset, those invalid in a scene skipped there only (`mpd.data.eval_contexts`).",
            "",
            markdown_table(["task", "scene", "source", "contexts", "skipped", "context seed", "file (sha256)"], crows),
            "",
        ]
    libs = prov.get("libraries") or {}
    if not libs and "libraries" in df.columns:
        libs = dict(kv.split("=", 1) for kv in str(_first(df, "libraries")).split(",") if "=" in kv)
    if libs:
        out += [
            "### Libraries",
            "",
            markdown_table(["library", "version"], [[k, str(v)] for k, v in sorted(libs.items())]),
            "",
        ]
    return out


# ---------------------------------------------------------------------------------------------- figures
def _save(fig, out: Path, formats: tuple[str, ...] = ("png",), dpi: int = 200) -> None:
    """Each format (PNG, and PDF when asked), written to a temporary name and renamed (a report being rebuilt is
    never half-written)."""
    from mpd.viz.scene import style

    out.parent.mkdir(parents=True, exist_ok=True)
    with style():
        box = getattr(fig, "_mpd_bbox", None)  # set by add_caption; else matplotlib finds it (one more draw)
        for ext in formats:
            kw = {"dpi": dpi} if ext == "png" else {"metadata": {"CreationDate": None}}  # no date: same bytes
            path = out.with_suffix(f".{ext}")
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            fig.savefig(tmp, format=ext, bbox_inches=box or "tight", pad_inches=0.05, **kw)
            os.replace(tmp, path)


FAILED = "failed: "  # the reason of an Entry that could not be drawn starts so


class FigureError(RuntimeError):
    """A report figure could not be drawn (the report was written without it)."""


def table_figures(d: pd.DataFrame, fig_dir: Path, cap: str, **save) -> list[Entry]:
    entries = []
    for kind in FIGURES:
        try:
            fig = kind.make(d)
        except Exception as e:  # one broken figure must not cost the whole report: noted, raised at the end
            log.debug("figure %s failed", kind.name, exc_info=True)
            entries.append(Entry(kind.name, kind.title, f"{FAILED}{type(e).__name__}: {e}"))
            continue
        if fig is None:
            entries.append(Entry(kind.name, kind.title, f"not in this run (needs {kind.needs})"))
            continue
        add_caption(fig, cap)
        _save(fig, fig_dir / kind.name, **save)
        entries.append(Entry(kind.name, kind.title))
    return entries


def _pick_histories(run_dir: Path, d: pd.DataFrame) -> list[tuple[str, str, str, Path, dict]]:
    """Per task and scene: the recorded context of MPD (else of the first method, in the paper's order, that has
    one). Returns (task, scene, method, history path, parameters)."""
    from mpd.viz.recording import _params_from_run

    files = sorted((run_dir / "histories").glob("*.npz")) if (run_dir / "histories").exists() else []
    found: dict[tuple[str, str], dict[str, tuple[Path, dict]]] = {}
    for f in files:
        try:
            _, params = load_history_params(f)
        except ValueError as e:  # a damaged history: the figure takes another context (or none)
            warnings.warn(f"{e}; skipped", stacklevel=2)
            continue
        if "task" not in params:
            params = {**_params_from_run(run_dir, params.get("cell_key", "")), **params}
        if "task" not in params:
            continue
        if (
            float(params.get("rotation_deg") or 0.0) != 0.0
            or str(params.get("parametrization") or "bspline") != "bspline"
        ):
            continue  # the scene figures show the main setting
        scene = EXTRA if params.get("extra_objects") else TRAIN
        by_method = found.setdefault((params["task"], scene), {})
        key = params["method"]
        # several recorded cells of one method (batch sizes, seeds): the largest batch, then the first context
        prev = by_method.get(key)
        rank = (-int(params.get("n_samples") or 0), int(params.get("context_index", 0)), f.name)
        if prev is None or rank < prev[2]:
            by_method[key] = (f, params, rank)
    out = []
    for task in task_order({t for t, _ in found}):
        for scene in (TRAIN, EXTRA):
            methods = found.get((task, scene))
            if not methods:
                continue
            m = "mpd" if "mpd" in methods else method_order(methods)[0]
            f, params, _ = methods[m]
            out.append((task, scene, m, f, params))
    return out


def load_history_params(path: Path):
    from mpd.viz.recording import load_history

    return load_history(path)


def _step_choice(labels: Sequence[str], k: int = 5) -> list[int]:
    """k steps evenly spaced over the recorded ones, first and last included."""
    n = len(labels)
    return sorted({int(round(i)) for i in np.linspace(0, n - 1, min(k, n))})


def history_figures(run_dir: Path, d: pd.DataFrame, fig_dir: Path, cap: str, **save) -> list[Entry]:
    """The denoising figure and the trajectory figure of one recorded context per task and scene."""
    from mpd.viz import scene as sc
    from mpd.viz.recording import run_task

    entries = []
    for task_name, scene, method, f, params in _pick_histories(run_dir, d):
        arrays, _ = load_history_params(f)
        stem = f"{task_name}-{'extra' if scene == EXTRA else 'train'}"
        what = f"{short_task(task_name)}, {scene}, {method_label(method)} (context {params.get('context_index', 0)})"
        try:
            task = run_task(run_dir, task_name)
        except Exception as e:
            entries.append(Entry(f"denoising-{stem}", f"Denoising: {what}", f"{FAILED}task not loadable: {e}"))
            continue
        env = task.env(scene == EXTRA, 0.0)
        if "steps_q" in arrays and len(arrays["steps_q"]):
            labels = [str(s) for s in arrays.get("steps_label", [f"step {i}" for i in range(len(arrays["steps_q"]))])]
            steps = [
                (
                    labels[i].replace(":", " "),
                    arrays["steps_q"][i],
                    arrays["steps_valid"][i] if "steps_valid" in arrays else None,
                )
                for i in _step_choice(labels, 5 if task.dim == 2 else 4)
            ]
            fig = sc.denoising_figure(task, env, steps)
            fig._mpd_note = what  # under the caption: a suptitle collides with the 3-D panels' titles
            add_caption(fig, cap)
            _save(fig, fig_dir / f"denoising-{stem}", **save)
            entries.append(Entry(f"denoising-{stem}", f"Samples during denoising / optimization: {what}"))
        else:
            entries.append(Entry(f"denoising-{stem}", f"Denoising: {what}", "no steps recorded"))
        fig = sc.trajectory_figure(
            task,
            env,
            arrays["q"],
            arrays["dq"],
            arrays["ddq"],
            arrays.get("valid"),
            title=f"{short_task(task_name)}, {scene}\n{method_label(method)}",
        )
        add_caption(fig, cap)
        _save(fig, fig_dir / f"trajectories-{stem}", **save)
        entries.append(Entry(f"trajectories-{stem}", f"Final trajectories: {what}"))
    return entries


# ------------------------------------------------------------------------------------------------ index
def _figures_md(entries: list[Entry], pdf: bool) -> list[str]:
    out = ["## Figures", ""]
    for e in entries:
        if e.skipped is None:
            links = (f"[PDF](figures/{e.name}.pdf) · " if pdf else "") + f"[PNG](figures/{e.name}.png)"
            out += [f"### {e.title}", "", f"![{e.title}](figures/{e.name}.png)", "", links, ""]
    skipped = [e for e in entries if e.skipped is not None]
    if skipped:
        out += ["### Not produced", ""] + [f"- {e.title}: {e.skipped}" for e in skipped] + [""]
    return out


def _recordings_md(run_dir: Path, recordings: list[Path], info: dict) -> list[str]:
    out = ["## Rerun recordings", ""]
    if not recordings:
        return out + ["No recorded contexts in this run (`record_contexts = 0`, or no history written).", ""]
    out += [
        f"One recording per recorded (cell, context); open them with `mpd view {info['run_id']}` "
        f"(or `mpd view {info['run_id']} --web` on a headless machine). Timelines: `denoising_step` (the batch at "
        "every step), `time` (the final trajectories, seconds).",
        "",
    ]
    out += [f"- [`{p.name}`](../recordings/{p.name})" for p in recordings]
    return out + [""]


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def build_report(
    run_dir: str | Path,
    recordings: bool = True,
    force_recordings: bool = False,
    formats: tuple[str, ...] = ("png",),
    dpi: int = 200,
    reference: str | Path | None = "auto",
    keep_going: bool = False,
) -> Path:
    """(Re)build ``run_dir/report/`` and, with ``recordings``, ``run_dir/recordings/``; returns ``index.md``.

    A figure that cannot be drawn is listed under "Not produced" and, unless ``keep_going``, raises
    :class:`FigureError` (naming the figure and the reason) once the rest of the report is written.

    ``formats`` and ``dpi``: of the figure files (the Markdown links the PNG and, when written, the PDF).
    ``reference``: the run this one is compared with in ``reproducibility.md``; ``"auto"``: the committed run of
    the same spec (``reports/<spec>/``) when there is one and it is not this run."""
    if "png" not in formats:
        raise ValueError(f"formats {formats!r}: the report shows the PNG files, so 'png' must be one of them")
    run_dir = Path(run_dir)
    df = read_results(run_dir)
    if df.empty:
        raise FileNotFoundError(f"{run_dir}: no results yet (results.parquet and parts/ are empty)")
    man = _manifest(run_dir)
    info = run_info(run_dir, man, df)
    cap = caption(info)
    d = prepare(df)
    out = run_dir / "report"
    fig_dir = out / "figures"
    if fig_dir.exists():  # figures of an earlier build that this table no longer makes must not linger
        shutil.rmtree(fig_dir)
    fig_dir.mkdir(parents=True)

    save = {"formats": tuple(formats), "dpi": dpi}
    entries = table_figures(d, fig_dir, cap, **save)
    entries += history_figures(run_dir, d, fig_dir, cap, **save)
    recs: list[Path] = []
    if recordings:
        from mpd.viz.recording import record_run

        recs = record_run(run_dir, force=force_recordings)
    elif (run_dir / "recordings").exists():
        recs = sorted((run_dir / "recordings").glob("*.rrd"))

    summary = summary_table(d)
    paper = paper_table(d)
    timing = timing_table(d)
    paired = paired_table(d, {t for t in d["task"].unique() if ee_goal(d, t)})
    contexts = contexts_summary(d)
    ref = default_reference(run_dir, info["spec"]) if reference == "auto" else reference
    repro_page, repro_line = reproducibility(run_dir, Path(ref) if ref is not None else None, info["spec"])
    _write(
        out / "summary.md",
        f"# Summary: {info['run_id']}\n\n{SUMMARY_NOTE}\n\n{summary}\n\n## Interquartile mean\n\n"
        f"{IQM_NOTE}\n\n{iqm_table(d)}\n\n## How many contexts\n\n{contexts}\n\n{contexts_table(d)}\n\n"
        f"## Validity by the authors' grid check\n\n{AUTHORS_GRID_NOTE}\n\n{authors_grid_table(d)}\n",
    )
    _write(out / "paired.md", f"# MPD against each baseline: {info['run_id']}\n\n{PAIRED_NOTE}\n\n{paired}\n")
    _write(out / "reproducibility.md", repro_page)
    _write(out / "paper.md", f"# The paper's numbers beside ours: {info['run_id']}\n\n{paper}")
    curves = has_curves(d)
    if curves:
        _write(
            out / "training.md",
            f"# Training recipes: {info['run_id']}\n\n{TRAINING_NOTE}\n\n{recipes_table(d)}\n\n"
            "![learning curves](figures/learning_curves.png)\n",
        )
    _write(
        out / "timing.md",
        f"# Timings: {info['run_id']}\n\nMean ± std over contexts; costs per gradient step.\n\n{timing}\n",
    )

    desc = (man.get("spec") or {}).get("description", "")
    lines = [f"# Run `{info['run_id']}`", ""]
    if desc:
        lines += [desc, ""]
    lines += [f"_{cap}_", ""]
    lines += _provenance_md(run_dir, man, df, info)
    lines += [
        "## Tables",
        "",
        "- [Summary: mean [95 % interval] over contexts, interquartile means, contexts needed](summary.md)",
        "- [Validity by the authors' grid check](summary.md#validity-by-the-authors-grid-check)",
        "- [MPD against each baseline on the same contexts](paired.md)",
        "- [Reproducibility against a reference run](reproducibility.md)",
        "- [The paper's numbers beside ours](paper.md)",
        "- [Timings](timing.md)",
        *(["- [Training recipes: learning curves and the recipe table](training.md)"] if curves else []),
        "",
    ]
    lines += [
        "### The paper's numbers beside ours",
        "",
        paper,
        "### MPD against each baseline",
        "",
        PAIRED_NOTE,
        "",
        paired,
        "",
        "### Summary",
        "",
        SUMMARY_NOTE,
        "",
        summary,
        "",
        contexts + " Per cell: [summary.md](summary.md#how-many-contexts).",
        "",
        "### Reproducibility",
        "",
        repro_line + " Per cell: [reproducibility.md](reproducibility.md).",
        "",
    ]
    lines += _figures_md(entries, "pdf" in formats)
    lines += _recordings_md(run_dir, recs, info)
    index = out / "index.md"
    _write(index, "\n".join(lines).rstrip() + "\n")
    failed = [e for e in entries if e.skipped is not None and e.skipped.startswith(FAILED)]
    if failed and not keep_going:
        more = f" (and {len(failed) - 1} more, listed in {index})" if len(failed) > 1 else ""
        raise FigureError(f"figure {failed[0].name!r} {failed[0].skipped}{more}")
    return index


__all__ = ["FigureError", "build_report", "caption", "run_info"]
