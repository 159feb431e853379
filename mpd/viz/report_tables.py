"""Markdown tables of a run: the summary (mean [95 % interval] over contexts), the paper's numbers beside ours,
the timings.

Deterministic: rows sorted by task (paper order), scene, method (paper order) and the variant axes; numbers
formatted with fixed precision.
"""

from __future__ import annotations

import functools
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from mpd.experiments.tracking import AXIS_PREFIXES
from mpd.viz.report_data import (
    BINARY,
    EXTRA,
    NOT_APPLICABLE,
    SUMMARY,
    TRAIN,
    VARIANT_AXES,
    applies,
    interval,
    mean_ci,
    mean_std,
    method_label,
    method_order,
    task_order,
)

PAPER_NUMBERS = Path(__file__).with_name("paper_numbers.toml")


def markdown_table(header: list[str], rows: list[list[str]], align: list[str] | None = None) -> str:
    """A GitHub Markdown table; ``align`` per column: "l" or "r"."""
    align = align or ["l"] * len(header)
    esc = lambda s: str(s).replace("|", "\\|").replace("\n", " ")  # noqa: E731
    lines = ["| " + " | ".join(esc(h) for h in header) + " |"]
    lines.append("| " + " | ".join("---:" if a == "r" else "---" for a in align) + " |")
    lines += ["| " + " | ".join(esc(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _varying(d: pd.DataFrame) -> list[str]:
    """Variant axes (and planner.* axes) with more than one value in the run: they become table columns."""
    cols = [a for a in VARIANT_AXES if a in d.columns] + sorted(c for c in d.columns if c.startswith(AXIS_PREFIXES))
    return [c for c in cols if d[c].astype(str).nunique() > 1]


def _groups(d: pd.DataFrame, extra_keys: list[str]):
    """(key dict, rows) per cell, in report order."""
    keys = ["task", "scene", "method", *extra_keys]
    tasks = {t: i for i, t in enumerate(task_order(d["task"].unique()))}
    methods = {m: i for i, m in enumerate(method_order(d["method"].unique()))}
    scenes = {TRAIN: 0, EXTRA: 1}
    out = []
    for key, g in d.groupby(keys, sort=False, dropna=False):
        k = dict(zip(keys, key))
        sort = (
            tasks[k["task"]],
            scenes.get(k["scene"], 2),
            methods[k["method"]],
            *[_sortable(k[c]) for c in extra_keys],
        )
        out.append((sort, k, g))
    out.sort(key=lambda t: t[0])
    return [(k, g) for _, k, g in out]


def _sortable(v):
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return (0, 0.0, "")
    if isinstance(v, int | float | np.integer | np.floating):
        return (1, float(v), "")
    return (2, 0.0, str(v))


def _fmt_axis(v) -> str:
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "–"
    if isinstance(v, float) and v.is_integer():
        return f"{v:g}"
    return str(v) if str(v) != "" else "–"


def summary_table(d: pd.DataFrame) -> str:
    """Mean [95 % interval] over contexts per task × scene × method (× the variant axes that vary in the run); ``–``
    where a metric does not apply (the EE errors of a joint-goal task)."""
    extra = _varying(d)
    mets = [m for m in SUMMARY if m[0] in d.columns]
    header = ["task", "scene", "method", *extra, "contexts", *[m[1] for m in mets]]
    rows = []
    for k, g in _groups(d, extra):
        row = [k["task"], k["scene"], method_label(k["method"]), *[_fmt_axis(k[c]) for c in extra], str(len(g))]
        row += [
            mean_ci(g[col], scale, fmt, col in BINARY) if applies(d, k["task"], col) else NOT_APPLICABLE
            for col, _, scale, fmt in mets
        ]
        rows.append(row)
    align = ["l"] * (3 + len(extra)) + ["r"] * (1 + len(mets))
    return markdown_table(header, rows, align)


# ------------------------------------------------------------------------------------------- timing table
def cost_columns(d: pd.DataFrame) -> list[str]:
    """Per-cost timing columns (``time_cost_<name>``), not the gradient total nor call counts."""
    return sorted(
        c
        for c in d.columns
        if c.startswith("time_cost_") and c != "time_cost_gradient" and not c.endswith("_calls") and d[c].notna().any()
    )


def gradient_calls(d: pd.DataFrame) -> pd.Series | None:
    for c in ("n_cost_gradient_calls", "time_cost_gradient_calls"):  # older runs stored the count as a time_
        if c in d.columns and d[c].notna().any():
            return d[c]
    return None


def timing_table(d: pd.DataFrame) -> str:
    """Per cell: total, sampling, network, cost-gradient time (s, mean ± std over contexts), gradient calls, and
    each cost's share of one gradient step (ms)."""
    extra = _varying(d)
    main = [
        (c, h)
        for c, h in (
            ("time_total", "total [s]"),
            ("time_sampling", "sampling [s]"),
            ("time_network", "network [s]"),
            ("time_cost_gradient", "cost gradient [s]"),
        )
        if c in d.columns
    ]
    costs = cost_columns(d)
    has_calls = gradient_calls(d) is not None
    header = ["task", "scene", "method", *extra, "contexts", *[h for _, h in main]]
    header += ["gradient calls"] if has_calls else []
    header += [f"{c.removeprefix('time_cost_')} [ms/step]" for c in costs]
    rows = []
    for k, g in _groups(d, extra):
        row = [k["task"], k["scene"], method_label(k["method"]), *[_fmt_axis(k[c]) for c in extra], str(len(g))]
        row += [mean_std(g[c], 1.0, "{:.3f}") for c, _ in main]
        calls = gradient_calls(g)
        if has_calls:
            row.append("–" if calls is None else mean_std(calls, 1.0, "{:.0f}"))
        for c in costs:
            per = g[c] / calls.replace(0, np.nan) if calls is not None else g[c]
            row.append(mean_std(per, 1000.0, "{:.3f}"))
        rows.append(row)
    align = ["l"] * (3 + len(extra)) + ["r"] * (len(header) - 3 - len(extra))
    return markdown_table(header, rows, align)


# ----------------------------------------------------------------------------------------- paper numbers
@functools.lru_cache(maxsize=1)
def paper_numbers() -> tuple[dict, ...]:
    """The numbers stated in the paper's text (``paper_numbers.toml``)."""
    with open(PAPER_NUMBERS, "rb") as f:
        return tuple(tomllib.load(f)["number"])


def _match(d: pd.DataFrame, num: dict) -> pd.DataFrame:
    """Rows of the cell that the paper's number describes: task, method, scene; rotation 0 and B-spline when the
    run has them; the paper's batch size when present, else the largest."""
    g = d[(d["task"] == num["task"]) & (d["method"] == num["method"])]
    scene = num.get("scene", "any")
    if scene == "any":
        g = g[~g["extra_objects"]] if (~g["extra_objects"]).any() else g
    else:
        g = g[g["extra_objects"] == (scene == "extra")]
    for axis, pref in (("rotation_deg", 0.0), ("parametrization", "bspline"), ("preset", "official")):
        if axis in g.columns and (g[axis] == pref).any():
            g = g[g[axis] == pref]
    if "n_samples" in g.columns and len(g):
        want = num.get("n_samples")
        g = g[g["n_samples"] == (want if want is not None and (g["n_samples"] == want).any() else g["n_samples"].max())]
    if "overrides" in g.columns and g["overrides"].astype(str).nunique() > 1:
        g = g[g["overrides"].astype(str) == ""] if (g["overrides"].astype(str) == "").any() else g.iloc[:0]
    return g


def paper_comparison(d: pd.DataFrame) -> tuple[pd.DataFrame, list[str]]:
    """One row per number stated in the paper for which the run has the cell (``number``: its index in
    :func:`paper_numbers`): (table, sentences by reference)."""
    sentences: list[str] = []
    rows = []
    for index, num in enumerate(paper_numbers()):
        g = _match(d, num)
        if num["metric"] not in g.columns or g[num["metric"]].notna().sum() == 0:
            continue
        if num["sentence"] not in sentences:
            sentences.append(num["sentence"])
        x = g[num["metric"]].astype(float).dropna() * float(num.get("scale", 1.0))
        ci = interval(g[num["metric"]].astype(float), float(num.get("scale", 1.0)), num["metric"] in BINARY)
        rows.append(
            {
                "number": index,
                "task": num["task"],
                "scene": {"train": TRAIN, "extra": EXTRA}.get(num.get("scene", "any"), TRAIN + " (not stated)"),
                "method": method_label(num["method"]),
                "metric": num["metric"],
                "unit": num.get("unit", ""),
                "paper": float(num["value"]),
                "paper_text": str(num["value"]),
                "ours": float(x.mean()),
                "ours_std": float(x.std(ddof=1)) if len(x) > 1 else float("nan"),
                "ours_lo": ci.lo,
                "ours_hi": ci.hi,
                "authors_check": _authors_check(g, num),
                "contexts": int(len(x)),
                "n_samples": int(g["n_samples"].iloc[0]) if "n_samples" in g.columns else None,
                "ref": sentences.index(num["sentence"]) + 1,
                "note": num.get("note", ""),
            }
        )
    return pd.DataFrame(rows), sentences


# a metric whose value depends on the validity check: the results column of the same metric by the authors' check
AUTHORS_CHECK = {"fraction_valid": "fraction_valid_authors_grid"}


def _authors_check(g: pd.DataFrame, num: dict):
    """The mean [95 % interval] of the number's metric by the authors' validity check (their SDF grid lookup), for
    the metrics that depend on it and rows that record it; None otherwise."""
    col = AUTHORS_CHECK.get(num["metric"])
    if col is None or col not in g.columns or g[col].notna().sum() == 0:
        return None
    return interval(g[col].astype(float), float(num.get("scale", 1.0)))


def _num(v: float, like: str) -> str:
    """Our number with the paper's precision (as it writes the number) plus one digit."""
    digits = len(like.split(".")[1]) if "." in like else 0
    return f"{v:.{digits + 1}f}"


def paper_table(d: pd.DataFrame) -> str:
    """The paper's numbers beside ours (mean [95 % interval] over contexts), with the sentences they come from."""
    t, sentences = paper_comparison(d)
    total = len(paper_numbers())
    if t.empty:
        return f"None of the {total} numbers stated in the paper's text has a matching cell in this run.\n"
    checked = t["authors_check"].notna().any()
    header = ["task", "scene", "method", "metric", "paper", "ours", *(["ours, authors' check"] if checked else [])]
    header += ["contexts", "B", "source"]
    rows = []
    for _, r in t.iterrows():
        unit = r["unit"] if r["unit"] in ("%", "°", "") else f" {r['unit']}"
        like = r["paper_text"]
        ours = _num(r["ours"], like) + (
            "" if np.isnan(r["ours_lo"]) else f" [{_num(r['ours_lo'], like)}, {_num(r['ours_hi'], like)}]"
        )
        a = r["authors_check"]
        theirs = (
            "–" if not hasattr(a, "lo") else f"{_num(a.value, like)} [{_num(a.lo, like)}, {_num(a.hi, like)}]{unit}"
        )
        rows.append(
            [
                r["task"],
                r["scene"],
                r["method"],
                r["metric"],
                f"{r['paper_text']}{unit}",
                f"{ours}{unit}",
                *([theirs] if checked else []),
                str(r["contexts"]),
                "–" if r["n_samples"] is None else str(r["n_samples"]),
                f"[{r['ref']}]" + (f" ({r['note']})" if r["note"] else ""),
            ]
        )
    out = ["Ours: mean [95 % interval] over contexts (bootstrap; Wilson's interval for success)."]
    if checked:
        out[0] += (
            " Ours, authors' check: the same trajectories counted valid by the authors' SDF grid lookup, the check "
            "the paper's numbers were measured with (summary.md, “Validity by the authors' grid check”)."
        )
    align = ["l", "l", "l", "l", "r", "r", *(["r"] if checked else []), "r", "r", "l"]
    out += ["", markdown_table(header, rows, align), ""]
    out.append(f"{len(t)} of the {total} numbers stated in the paper's text have a matching cell in this run.")
    out.append("")
    out += [f"[{i}] “{s}”  " for i, s in enumerate(sentences, 1)]
    ee = ee_aggregates_table(d)
    if ee:
        out += ["", "## End-effector errors: every aggregate", "", EE_AGGREGATES_NOTE, "", ee]
    return "\n".join(out) + "\n"


# the candidate aggregates of an end-effector error number: (label, results column); the first of each metric is
# the paper's definition (reports/ee-error-decomposition/README.md has the evidence)
EE_AGGREGATES = {
    "ee_pos_error": (
        ("mean over the valid samples, SE(3)-log translation", "ee_pos_error"),
        ("mean over the valid samples, Euclidean", "ee_pos_error_euclidean"),
        ("best valid sample, SE(3)-log translation", "best_ee_pos_error"),
        ("best valid sample, Euclidean", "best_ee_pos_error_euclidean"),
    ),
    "ee_ori_error_deg": (
        ("mean over the valid samples", "ee_ori_error_deg"),
        ("best valid sample", "best_ee_ori_error_deg"),
    ),
}
EE_AGGREGATES_NOTE = (
    "Each end-effector number of the paper against every aggregate the results hold: per context the mean over "
    "the valid samples or the best valid sample (lowest SE(3)-log position error), the position error as the "
    "translation part of log(T_goal T_ee⁻¹) or the Euclidean distance; then the mean [95 % interval] and the "
    "median over contexts. ★ marks the paper's definition (“reported only for valid trajectories”, the mean; the "
    "authors' SE(3)-log error): the rows above use it. Evidence: `reports/ee-error-decomposition/README.md`."
)


def ee_aggregates_table(d: pd.DataFrame) -> str:
    """Every aggregate of the paper's end-effector numbers that the run has a cell for ('' when none)."""
    rows = []
    for num in paper_numbers():
        cands = EE_AGGREGATES.get(num["metric"])
        if cands is None:
            continue
        g = _match(d, num)
        if num["metric"] not in g.columns or g[num["metric"]].notna().sum() == 0:
            continue
        scale = float(num.get("scale", 1.0))
        unit = num.get("unit", "")
        unit = unit if unit in ("%", "°", "") else f" {unit}"
        like = str(num["value"])
        scene = {"train": TRAIN, "extra": EXTRA}.get(num.get("scene", "any"), TRAIN + " (not stated)")
        for k, (label, col) in enumerate(cands):
            if col not in g.columns:
                continue
            x = g[col].astype(float)
            ci = interval(x, scale)
            med = float(x.dropna().median()) * scale if x.notna().any() else float("nan")
            ours = _num(ci.value, like) + (
                "" if not np.isfinite(ci.lo) else f" [{_num(ci.lo, like)}, {_num(ci.hi, like)}]"
            )
            rows.append(
                [
                    num["task"],
                    scene,
                    method_label(num["method"]),
                    num["metric"],
                    f"{like}{unit}",
                    ("★ " if k == 0 else "") + label,
                    f"{ours}{unit}",
                    f"{_num(med, like)}{unit}",
                    str(int(x.notna().sum())),
                ]
            )
    if not rows:
        return ""
    header = ["task", "scene", "method", "metric", "paper", "aggregate", "ours: mean [95 %]", "median", "contexts"]
    return markdown_table(header, rows, ["l", "l", "l", "l", "r", "l", "r", "r", "r"])
