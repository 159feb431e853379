"""The report's statistics: intervals of the summary's means, the interquartile means, MPD against each baseline
on the same contexts, how many contexts a claim needs, and how this run reproduces a reference run.

Intervals are those of :mod:`mpd.stats` (95 %: a seeded percentile bootstrap over a cell's contexts, Wilson's
interval for success), so a rebuild of the report gives the same Markdown.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from mpd import stats
from mpd.viz.report_data import SUMMARY, fmt_estimate, main_slice, method_label, method_order, scaled, task_order
from mpd.viz.report_tables import _fmt_axis, _groups, _varying, markdown_table

# continuous metrics with skewed distributions over contexts (failed contexts at 0, a few long paths): the
# interquartile mean beside the mean
SKEWED = ("fraction_valid", "vendi", "smoothness", "path_length")
# MPD against each baseline: (column, header, scale, format, higher is better)
PAIRED = (
    ("success", "Δ success [pp]", 100.0, "{:+.1f}", True),
    ("fraction_valid", "Δ fraction valid [pp]", 100.0, "{:+.1f}", True),
    ("vendi", "Δ Vendi", 1.0, "{:+.2f}", True),
    ("ee_pos_error", "Δ EE pos. error [cm]", 100.0, "{:+.2f}", False),
    ("ee_ori_error_deg", "Δ EE ori. error [°]", 1.0, "{:+.2f}", False),
)
REFERENCE_METHOD = "mpd"
TARGET_HALF_WIDTH = 0.05  # of fraction valid: the precision the README's advice on context counts aims at


def iqm_table(d: pd.DataFrame) -> str:
    """Interquartile mean [95 % interval] of the skewed metrics, per cell."""
    extra = _varying(d)
    mets = [m for m in SUMMARY if m[0] in SKEWED and m[0] in d.columns]
    header = ["task", "scene", "method", *extra, "contexts", *[f"IQM {m[1]}" for m in mets]]
    rows = []
    for k, g in _groups(d, extra):
        row = [k["task"], k["scene"], method_label(k["method"]), *[_fmt_axis(k[c]) for c in extra], str(len(g))]
        for col, _, scale, fmt in mets:
            e = stats.bootstrap(pd.to_numeric(g[col], errors="coerce"), "iqm")
            row.append(fmt_estimate(scaled(e, scale), fmt))
        rows.append(row)
    return markdown_table(header, rows, ["l"] * (3 + len(extra)) + ["r"] * (1 + len(mets)))


# ------------------------------------------------------------------------------------- paired comparisons
def _pair_key(g: pd.DataFrame) -> pd.DataFrame:
    return g.set_index(["seed", "context_index"]).sort_index()


def paired_rows(d: pd.DataFrame) -> list[dict]:
    """MPD against each other method, per task and scene, on the contexts both planned (the paper's setting of
    the variant axes, as the figures): per metric the mean difference MPD - baseline and the probability that
    MPD is better on a context, each with its 95 % interval from the same resampled contexts."""
    d, _ = main_slice(d)
    out = []
    for task in task_order(d["task"].unique()):
        for scene in (s for s in ("training environment", "extra objects") if (d["scene"] == s).any()):
            g = d[(d["task"] == task) & (d["scene"] == scene)]
            if REFERENCE_METHOD not in set(g["method"]):
                continue
            ref = _pair_key(g[g["method"] == REFERENCE_METHOD])
            for m in method_order(g["method"].unique()):
                if m == REFERENCE_METHOD:
                    continue
                base = _pair_key(g[g["method"] == m])
                common = ref.index.intersection(base.index)
                row = {"task": task, "scene": scene, "method": m, "contexts": len(common), "metrics": {}}
                for col, _, _, _, higher in PAIRED:
                    if col in g.columns and g[col].notna().any():
                        a = pd.to_numeric(ref.loc[common, col], errors="coerce").to_numpy(float)
                        b = pd.to_numeric(base.loc[common, col], errors="coerce").to_numpy(float)
                        row["metrics"][col] = stats.paired(a, b, higher_is_better=higher)
                out.append(row)
    return out


def paired_table(d: pd.DataFrame, ee_tasks: set[str] | None = None) -> str:
    """The paired comparisons as Markdown; ``ee_tasks``: tasks with an end-effector goal (their EE columns)."""
    rows = paired_rows(d)
    if not rows:
        return f"No {method_label(REFERENCE_METHOD)} cell in this run: nothing to compare it with."
    ee_tasks = ee_tasks or set()
    cols = [p for p in PAIRED if any(p[0] in r["metrics"] for r in rows)]
    cols = [p for p in cols if not p[0].startswith("ee_") or any(r["task"] in ee_tasks for r in rows)]
    header = ["task", "scene", f"{method_label(REFERENCE_METHOD)} vs", "contexts"]
    for col, head, *_ in cols:
        header += [head, "P(MPD better)"] if col == "fraction_valid" else [head]
    table = []
    for r in rows:
        line = [r["task"], r["scene"], method_label(r["method"]), str(r["contexts"])]
        for col, _, scale, fmt, _ in cols:
            p = r["metrics"].get(col)
            missing = p is None or (col.startswith("ee_") and r["task"] not in ee_tasks)
            e = None if missing else p.difference
            text = "–" if e is None else fmt_estimate(scaled(e, scale), fmt, True)
            if e is not None and 0 < e.n < r["contexts"]:  # e.g. Vendi needs two valid trajectories on both sides
                text += f" ({e.n} contexts)"
            line.append(text)
            if col == "fraction_valid":
                line.append("–" if missing else fmt_estimate(p.p_improvement, "{:.2f}"))
        table.append(line)
    return markdown_table(header, table, ["l", "l", "l"] + ["r"] * (len(header) - 3))


PAIRED_NOTE = (
    "MPD minus each baseline on the same contexts (same start, goal and noise seed), mean [95 % interval] from a "
    "bootstrap over contexts that resamples the pairs; **bold**: the interval excludes 0 (for EE errors, lower is "
    "better). P(MPD better): the probability that MPD's fraction valid is higher on a context (ties count one half). "
    "Where the two methods tie on every context (both succeed everywhere), the interval is the point 0: the "
    "contexts hold no sign of a difference, not a proof that there is none."
)


# ---------------------------------------------------------------------------- the authors' grid check
GRID_COLUMNS = ("fraction_valid_authors_grid", "n_flips_valid_to_invalid", "n_flips_invalid_to_valid")


def authors_grid_table(d: pd.DataFrame) -> str:
    """Per cell: fraction valid by mpd's checker (the exact SDF) and by the authors' (their SDF grid with its
    off-by-one node, :class:`mpd.envs.grid.AuthorsGridSDF`), their paired difference over the contexts (authors'
    − mpd's, pp, 95 % bootstrap) and the verdicts it flips, summed over the cell's trajectories. Rows without
    the columns (runs before the check was recorded) are left out, and said so."""
    have = all(c in d.columns for c in GRID_COLUMNS)
    rows_with = d[d[GRID_COLUMNS[0]].notna()] if have else d.iloc[:0]
    if rows_with.empty:
        return "This run's rows predate the authors'-grid check (`fraction_valid_authors_grid`): nothing to show."
    extra = _varying(d)
    header = ["task", "scene", "method", *extra, "contexts", "trajectories", "fraction valid, mpd [%]"]
    header += ["authors' grid [%]", "authors' − mpd [pp]", "valid → invalid", "invalid → valid"]
    table = []
    for k, g in _groups(rows_with, extra):
        ours = pd.to_numeric(g["fraction_valid"], errors="coerce").to_numpy()
        theirs = pd.to_numeric(g["fraction_valid_authors_grid"], errors="coerce").to_numpy()
        diff = stats.paired(theirs, ours).difference
        n = int(pd.to_numeric(g["n_samples"], errors="coerce").sum()) if "n_samples" in g else None
        table.append(
            [
                k["task"],
                k["scene"],
                method_label(k["method"]),
                *[_fmt_axis(k[c]) for c in extra],
                str(len(g)),
                "–" if n is None else str(n),
                f"{100 * np.nanmean(ours):.1f}",
                f"{100 * np.nanmean(theirs):.1f}",
                fmt_estimate(scaled(diff, 100.0), "{:+.1f}", True),
                str(int(g["n_flips_valid_to_invalid"].sum())),
                str(int(g["n_flips_invalid_to_valid"].sum())),
            ]
        )
    note = ""
    if len(rows_with) < len(d):
        note = f"\n\n{len(d) - len(rows_with)} rows predate the check and are left out."
    return markdown_table(header, table, ["l"] * (3 + len(extra)) + ["r"] * 7) + note


AUTHORS_GRID_NOTE = (
    "mpd counts a trajectory valid by the exact signed distance of every robot sphere to every obstacle (margin 0). "
    "The authors' code reads an SDF grid at a node one cell off the nearest one; the row records what their check "
    "would say of the same trajectories. The two disagree near obstacles only, so the methods whose samples end "
    "close to obstacles (those guided by the collision cost) flip most. The paper's fraction-valid numbers were "
    'measured with the authors\' check (docs/PAPER_VS_CODE.md, "validity ground truth").'
)


# -------------------------------------------------------------------------------------- number of contexts
def contexts_rows(d: pd.DataFrame) -> list[dict]:
    """Per cell: the half-width of the 95 % interval of fraction valid at this run's contexts, the per-context
    standard deviation, and the contexts a half-width of ``TARGET_HALF_WIDTH`` would need."""
    if "fraction_valid" not in d.columns:
        return []
    extra = _varying(d)
    out = []
    for k, g in _groups(d, extra):
        x = stats.finite(pd.to_numeric(g["fraction_valid"], errors="coerce"))
        e = stats.bootstrap(x)
        sd = float(np.std(x, ddof=1)) if len(x) > 1 else float("nan")
        out.append(
            {
                **k,
                "extra": {c: k[c] for c in extra},
                "n": len(x),
                "half_width": e.half_width,
                "sd": sd,
                "needed": stats.contexts_needed(sd, TARGET_HALF_WIDTH) if np.isfinite(sd) else None,
            }
        )
    return out


def contexts_summary(d: pd.DataFrame) -> str:
    rows = [r for r in contexts_rows(d) if np.isfinite(r["half_width"])]
    if not rows:
        return "Too few contexts per cell for an interval of fraction valid."
    hw = np.array([r["half_width"] for r in rows])
    need = np.array([r["needed"] for r in rows])
    ns = sorted({r["n"] for r in rows})
    return (
        f"At {', '.join(map(str, ns))} contexts per cell, the 95 % interval of fraction valid is ± "
        f"{100 * np.median(hw):.1f} pp wide in the median cell (± {100 * hw.max():.1f} pp at most); ± "
        f"{100 * TARGET_HALF_WIDTH:.0f} pp in every cell would need {int(need.max())} contexts (median cell: "
        f"{int(np.median(need))})."
    )


def contexts_table(d: pd.DataFrame) -> str:
    rows = contexts_rows(d)
    extra = _varying(d)
    header = ["task", "scene", "method", *extra, "contexts", "± fraction valid [pp]", "sd per context [pp]"]
    header.append(f"contexts for ± {100 * TARGET_HALF_WIDTH:.0f} pp")
    table = []
    for r in rows:
        table.append(
            [
                r["task"],
                r["scene"],
                method_label(r["method"]),
                *[_fmt_axis(r["extra"][c]) for c in extra],
                str(r["n"]),
                "–" if not np.isfinite(r["half_width"]) else f"{100 * r['half_width']:.1f}",
                "–" if not np.isfinite(r["sd"]) else f"{100 * r['sd']:.1f}",
                "–" if r["needed"] is None else str(r["needed"]),
            ]
        )
    return markdown_table(header, table, ["l"] * (3 + len(extra)) + ["r"] * 4)


# ---------------------------------------------------------------------------------------- reproducibility
def default_reference(run_dir: Path, spec_name: str) -> Path | None:
    """The committed run of the same spec (``reports/<spec>/``) when there is one and it is not this run."""
    from mpd.paths import REPO_ROOT

    ref = Path(REPO_ROOT) / "reports" / str(spec_name)
    if not (ref / "results.parquet").exists() or ref.resolve() == Path(run_dir).resolve():
        return None
    return ref


def _shown_path(p: Path) -> str:
    from mpd.paths import REPO_ROOT

    try:
        return str(Path(p).resolve().relative_to(Path(REPO_ROOT).resolve()))
    except ValueError:
        return str(p)


def reproducibility(run_dir: Path, reference: Path | None, spec_name: str) -> tuple[str, str]:
    """(the page, one line for the index): every cell of this run against the reference run."""
    from mpd.experiments.reproduce import compare, differing

    if reference is None:
        from mpd.paths import REPO_ROOT

        committed = Path(REPO_ROOT) / "reports" / str(spec_name)
        if committed.resolve() == Path(run_dir).resolve():
            line = (
                f"This run is the committed reference of spec `{spec_name}`: a rerun's report compares itself with "
                "it (`mpd report RUN`), and `mpd runs compare --equivalent "
                f"reports/{spec_name} RUN` asserts that the rerun reproduces it."
            )
        else:
            line = "No reference run (none committed for this spec): `mpd report RUN --reference REFERENCE`."
        return f"# Reproducibility\n\n{line}\n", line
    comp = compare(reference, run_dir)
    counts = comp.cells["level"].value_counts()
    levels = ", ".join(f"{counts[lv]} {lv}" for lv in ("bit-identical", "equivalent", "differs") if lv in counts)
    others = ", ".join(f"{counts[lv]} {lv}" for lv in ("only in A", "only in B") if lv in counts)
    others = others.replace("only in A", "only in the reference").replace("only in B", "only in this run")
    verdict = "reproduces it" if comp.equivalent else "does not reproduce it: " + "; ".join(comp.failures)
    line = (
        f"Against the reference run `{_shown_path(reference)}`: {levels}{', ' + others if others else ''} "
        f"(of {len(comp.cells)} cells); this run {verdict}."
    )
    keys = [k for k in comp.keys if k not in ("seed",) and comp.cells[k].nunique() > 1]
    rows = []
    for _, r in comp.cells.iterrows():
        diffs = differing(comp, r)
        rows.append(
            [
                *[str(r[k]) or "–" for k in keys],
                str(r["level"]).replace("only in A", "only in the reference").replace("only in B", "only here"),
                "; ".join(f"{x.metric} {x['diff']:+.3g} [{x.lo:+.3g}, {x.hi:+.3g}]" for _, x in diffs.iterrows())
                or "–",
                str(r.get("causes") or "") or "–",
            ]
        )
    page = [
        "# Reproducibility",
        "",
        line,
        "",
        "Per cell: **bit-identical** (every metric equal on every context), **equivalent** (not identical, no "
        "metric differs beyond noise: a paired permutation test per metric over the contexts, two-sample where "
        "the task file or dataset changed, false-discovery rate 5 % over all cells and metrics) or **differs** "
        "(the metrics that do, this run minus the reference, with their 95 % interval), and what differs between "
        "the two runs' inputs (task file, dataset, model, code, device, CPU type). Times are not compared.",
        "",
        markdown_table([*keys, "level", "differs (this run - reference)", "inputs that differ"], rows),
        "",
    ]
    return "\n".join(page), line


__all__ = [
    "PAIRED_NOTE",
    "contexts_summary",
    "contexts_table",
    "default_reference",
    "iqm_table",
    "paired_rows",
    "paired_table",
    "reproducibility",
]
