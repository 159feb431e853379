"""Did run B reproduce run A? Per cell and metric: bit-identical, equivalent within noise, or different, and why.

Two runs of one spec plan the same contexts with the same seeds, so a cell's rows pair up by context: the test
is a paired sign-flip permutation test of the mean difference (B - A). Where a cell's task file or dataset
changed, the contexts are other draws and the test is a two-sample permutation test instead. A (cell, metric)
*differs* when its p-value survives the Benjamini-Hochberg procedure at ``mpd.stats.ALPHA`` over every
non-identical (cell, metric) of the comparison (and its difference exceeds ``tol``): when B is a faithful rerun,
the chance of flagging anything at all is at most 5 %. Times are not compared: they measure the machine.

Levels of a cell: ``bit-identical`` (every compared metric equal on every context), ``equivalent`` (not
identical, nothing differs beyond noise: e.g. a model trained on another CPU type), ``differs``, ``only in A`` /
``only in B``. ``equivalent`` is "no difference detectable with these contexts": the interval of each difference
says how large a difference could still hide.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from mpd import stats
from mpd.experiments.results import read_results
from mpd.experiments.tracking import SUMMARY_METRICS, _key, cell_columns

# per-context metrics compared (not the times: they depend on the machine and its load)
COMPARED = (*(m for m in SUMMARY_METRICS if not m.startswith("time_")), "best_path_length")
# inputs that fix a cell's contexts and data: a reproduction must keep them; the model may differ (training is
# not bit-reproducible across CPU types) and the report says so
FIXED_INPUTS = ("task_hash", "dataset_hash")
# why two runs' rows of a cell may differ: (column, what it means)
CAUSES = (
    ("task_hash", "task file"),
    ("dataset_hash", "dataset"),
    ("model_hash", "model"),
    ("git_commit", "code"),
    ("device", "device"),
)
LEVELS = ("bit-identical", "equivalent", "differs", "only in A", "only in B")


@dataclass
class Comparison:
    """``metrics``: one row per (cell, metric); ``cells``: one row per cell with its level and causes;
    ``failures``: why B is not equivalent to A (empty when it is)."""

    metrics: pd.DataFrame
    cells: pd.DataFrame
    keys: list[str]
    failures: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def equivalent(self) -> bool:
        return not self.failures


def _manifest(run_dir: Path) -> dict:
    p = Path(run_dir) / "manifest.json"
    return json.loads(p.read_text()) if p.exists() else {}


def _values(g: pd.DataFrame, col: str) -> set[str]:
    return {_key(v) for v in g[col]} if col in g.columns else set()


def _by_context(g: pd.DataFrame, col: str) -> pd.Series:
    return pd.to_numeric(g.set_index("context_index")[col], errors="coerce").astype(float).sort_index()


def _compare_metric(ga: pd.DataFrame, gb: pd.DataFrame, col: str, is_paired: bool) -> dict:
    va, vb = _by_context(ga, col), _by_context(gb, col)
    same_contexts = va.index.equals(vb.index)
    identical = same_contexts and np.array_equal(va.to_numpy(), vb.to_numpy(), equal_nan=True)
    if is_paired:
        common = va.index.intersection(vb.index)
        a, b = va.loc[common].to_numpy(), vb.loc[common].to_numpy()
        diff = stats.paired(b, a).difference
        p = 1.0 if identical else stats.paired_pvalue(b, a)
    else:
        a, b = va.to_numpy(), vb.to_numpy()
        diff = stats.unpaired_difference(b, a)
        p = 1.0 if identical else stats.two_sample_pvalue(b, a)
    return {
        "metric": col,
        "test": "paired" if is_paired else "two-sample",
        "n": diff.n,
        "mean_a": float(np.nanmean(va)) if np.isfinite(va).any() else np.nan,
        "mean_b": float(np.nanmean(vb)) if np.isfinite(vb).any() else np.nan,
        "diff": diff.value,
        "lo": diff.lo,
        "hi": diff.hi,
        "p": p,
        "identical": identical,
    }


def compare(run_a: Path, run_b: Path, tol: float = 0.0, alpha: float = stats.ALPHA) -> Comparison:
    """Compare run B with run A (the reference), cell by cell and metric by metric."""
    a, b = read_results(run_a), read_results(run_b)
    if a.empty or b.empty:
        raise FileNotFoundError(f"{run_a if a.empty else run_b}: no results")
    keys = [c for c in cell_columns(a) if c in set(cell_columns(b))]
    for df in (a, b):
        df["_cell"] = list(zip(*[df[k].map(_key) for k in keys]))
    ga_all, gb_all = dict(tuple(a.groupby("_cell", sort=False))), dict(tuple(b.groupby("_cell", sort=False)))
    cpu_a, cpu_b = _manifest(run_a).get("cpu"), _manifest(run_b).get("cpu")
    metric_rows, cell_rows = [], []
    for cell in sorted(set(ga_all) | set(gb_all)):
        base = dict(zip(keys, cell))
        ga, gb = ga_all.get(cell), gb_all.get(cell)
        if ga is None or gb is None:
            cell_rows.append({**base, "level": "only in B" if ga is None else "only in A", "causes": ""})
            continue
        changed = [c for c, _ in CAUSES if c in a.columns and c in b.columns and _values(ga, c) != _values(gb, c)]
        causes = [name for c, name in CAUSES if c in changed]
        if cpu_a and cpu_b and cpu_a != cpu_b:
            causes.append("CPU type")
        is_paired = not any(c in changed for c in FIXED_INPUTS)
        same_contexts = set(ga["context_index"]) == set(gb["context_index"])
        for col in COMPARED:
            if col in a.columns and col in b.columns:
                metric_rows.append({**base, **_compare_metric(ga, gb, col, is_paired)})
        cell_rows.append(
            {
                **base,
                "contexts_a": len(ga),
                "contexts_b": len(gb),
                "same_contexts": same_contexts,
                "inputs_changed": ",".join(changed),
                "causes": ", ".join(causes),
                "level": None,
            }
        )
    metrics = pd.DataFrame(metric_rows)
    cells = pd.DataFrame(cell_rows)
    if metrics.empty:
        metrics = pd.DataFrame(columns=[*keys, "metric", "identical", "p", "diff", "lo", "hi"])
    metrics["differs"] = False
    tested = ~metrics["identical"].astype(bool)
    if tested.any():
        found = stats.discoveries(metrics.loc[tested, "p"].to_numpy(), alpha)
        metrics.loc[tested, "differs"] = found & (metrics.loc[tested, "diff"].abs().to_numpy() > tol)
    levels = []
    for _, r in cells.iterrows():
        if isinstance(r.get("level"), str):  # a cell of one run only
            levels.append(r["level"])
            continue
        m = metrics[np.logical_and.reduce([metrics[k] == r[k] for k in keys])] if len(metrics) else metrics
        if m["differs"].any():
            levels.append("differs")
        elif m["identical"].all() and bool(r.get("same_contexts", True)):
            levels.append("bit-identical")
        else:
            levels.append("equivalent")
    cells["level"] = levels
    return Comparison(metrics, cells, keys, *_verdict(metrics, cells, keys, alpha))


def _verdict(metrics: pd.DataFrame, cells: pd.DataFrame, keys: list[str], alpha: float):
    failures, notes = [], []
    counts = cells["level"].value_counts()
    notes.append(", ".join(f"{counts[lv]} {lv}" for lv in LEVELS if lv in counts) + f" (of {len(cells)} cells)")
    for lv in ("only in A", "only in B"):
        if lv in counts:
            failures.append(f"{counts[lv]} cells {lv}")
    if "differs" in counts:
        bad = metrics[metrics["differs"]]
        failures.append(
            f"{counts['differs']} cells differ beyond noise (false-discovery rate {alpha:g}): "
            + ", ".join(sorted(set(bad["metric"])))
        )
    changed = cells.get("inputs_changed", pd.Series(dtype=str)).fillna("")
    for col in FIXED_INPUTS:
        n = int(changed.str.contains(col).sum())
        if n:
            failures.append(f"{col} changed in {n} cells")
    if "same_contexts" in cells and (cells["same_contexts"] == False).any():  # noqa: E712 (NaN for one-run cells)
        failures.append(f"{int((cells['same_contexts'] == False).sum())} cells have other contexts")  # noqa: E712
    if changed.str.contains("model_hash").any():
        notes.append("model hashes differ in some cells: their rows can at best be equivalent, not bit-identical")
    notes.append("times are not compared (they measure the machine)")
    return failures, notes


def differing(comp: Comparison, cell: pd.Series) -> pd.DataFrame:
    """The (cell, metric) rows of one cell that differ beyond noise."""
    m = comp.metrics
    if m.empty:
        return m
    return m[np.logical_and.reduce([m[k] == cell[k] for k in comp.keys]) & m["differs"]]


def format_comparison(comp: Comparison) -> str:
    """Text for the terminal: per cell its level, the metrics that differ (B - A with its 95 % interval) and the
    inputs that changed; then the counts and the failures of an equivalence assertion."""
    cells = comp.cells
    shown = [k for k in comp.keys if cells[k].nunique() > 1] or comp.keys[:2]
    rows = []
    for _, r in cells.iterrows():
        diffs = differing(comp, r)
        rows.append(
            {
                **{k: r[k] for k in shown},
                "level": r["level"],
                "differs": "; ".join(
                    f"{d.metric} {d['diff']:+.4f} [{d.lo:+.4f}, {d.hi:+.4f}]" for _, d in diffs.iterrows()
                ),
                "causes": r.get("causes", "") or "",
            }
        )
    with pd.option_context("display.width", 240, "display.max_columns", 30, "display.max_rows", 1000):
        lines = [pd.DataFrame(rows).to_string(index=False)]
    lines += comp.notes
    lines += [f"failure: {f}" for f in comp.failures]
    return "\n".join(lines)


__all__ = ["CAUSES", "COMPARED", "FIXED_INPUTS", "LEVELS", "Comparison", "compare", "differing", "format_comparison"]
