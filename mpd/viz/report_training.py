"""Learning curves of a training-recipe study: prior quality against the CPU-minutes its model cost, one line per
recipe, made when a run varies ``training.steps`` (spec axes ``training.*``, e.g. ``recipe-study-2d``).

A recipe is the set of training values of a cell other than ``steps``; its points are its budgets. The x-axis is the
model's training wall time (``model_train_s``: for a wsd budget, the stable phase it resumed from included, so the
cost of that model trained alone). Each point is the mean over the cell's contexts with its 95 % interval (Wilson's
for success, a bootstrap for the rest), as in the summary table.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from mpd.stats import Estimate
from mpd.viz.report_data import TRAIN, fmt_estimate, interval, method_label, short_task, task_order
from mpd.viz.report_style import plain_log_ticks
from mpd.viz.scene import style

TRAINING_NOTE = (
    "One row per recipe and budget, training scene; mean [95 % interval] over the cell's contexts (Wilson's interval "
    "for success). `train [min]` is the model's training wall time, for a wsd budget including the stable phase it "
    "resumed from: the cost of that model trained alone on this machine."
)
# distinct at a glance, in print and for the common colour-vision deficiencies (Okabe-Ito)
RECIPE_COLORS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000")
METRICS = (("success", "success [%]", 100.0, True), ("fraction_valid", "fraction valid [%]", 100.0, False))
DIVERSITY = ("vendi", "diversity (Vendi)", 1.0, False)
# the goal precision of an end-effector-goal task's samples (SE(3) log, mean over the valid samples); a prior can be
# valid and diverse and still not reach the goal pose, which only these columns show
GOAL = (
    ("ee_pos_error", "EE pos. error [cm]", 100.0, "{:.1f}"),
    ("ee_ori_error_deg", "EE ori. error [°]", 1.0, "{:.1f}"),
)


def recipe_columns(d: pd.DataFrame) -> list[str]:
    """The training and network columns that vary in the run, ``steps`` excluded (they name the recipes)."""
    cols = sorted(c for c in d.columns if c.startswith(("training.", "model.")) and c != "training.steps")
    return [c for c in cols if d[c].astype(str).nunique() > 1]


def has_curves(d: pd.DataFrame) -> bool:
    return "training.steps" in d.columns and d["training.steps"].dropna().nunique() > 1 and "model_train_s" in d.columns


def recipe_label(row: pd.Series | dict, cols: list[str]) -> str:
    return ", ".join(f"{c.removeprefix('training.')}={row[c]}" for c in cols) or "recipe"


def curve_points(d: pd.DataFrame) -> pd.DataFrame:
    """One row per (task, method, recipe, budget): steps, training minutes and each metric's estimate."""
    d = d[d["training.steps"].notna() & (d["scene"] == TRAIN)]
    cols = recipe_columns(d)
    out = []
    keys = ["task", "method", *cols, "training.steps"]
    for key, g in d.groupby(keys, sort=False, dropna=False):
        k = dict(zip(keys, key))
        row = {
            "task": k["task"],
            "method": k["method"],
            "recipe": recipe_label(k, cols),
            "steps": int(k["training.steps"]),
            "minutes": float(pd.to_numeric(g["model_train_s"], errors="coerce").mean()) / 60.0,
            "contexts": len(g),
        }
        for col, _, scale, binary in (*METRICS, DIVERSITY):
            row[col] = interval(g[col], scale, binary=binary) if col in g.columns else None
        for col, _, scale, _ in GOAL:
            v = pd.to_numeric(g[col], errors="coerce") if col in g.columns else pd.Series(dtype=float)
            # a joint-goal task's samples end on their goal by construction (the last control point is the goal):
            # zero up to the FK's rounding (< 10 um, < 1e-3 deg), not a measurement of the prior
            row[col] = interval(v.dropna(), scale) if (v.abs() > 1e-5).any() else None
        out.append(row)
    return pd.DataFrame(out).sort_values(["task", "method", "recipe", "steps"]) if out else pd.DataFrame()


def learning_curve_figure(d: pd.DataFrame) -> Figure | None:
    """Per task (rows): success, fraction valid and Vendi against training minutes, one line per recipe."""
    if not has_curves(d):
        return None
    pts = curve_points(d)
    if pts.empty:
        return None
    tasks = task_order(pts["task"].unique())
    recipes = sorted(pts["recipe"].unique())
    colors = {r: RECIPE_COLORS[i % len(RECIPE_COLORS)] for i, r in enumerate(recipes)}
    panels = (*METRICS, DIVERSITY)
    if pts[GOAL[0][0]].notna().any():  # an end-effector-goal task: how far its samples end from the goal pose
        panels += ((GOAL[0][0], GOAL[0][1], GOAL[0][2], False),)
    with style():
        fig = Figure(figsize=(3.0 * len(panels) + 0.4, 2.5 * len(tasks) + 0.9), layout="constrained")
        axes = fig.subplots(len(tasks), len(panels), squeeze=False)
        for r, task in enumerate(tasks):
            pt = pts[pts["task"] == task]
            for c, (col, label, _, _) in enumerate(panels):
                ax = axes[r, c]
                if not any(isinstance(e, Estimate) for e in pt[col]):  # the goal error of a joint-goal task
                    ax.text(0.5, 0.5, "joint-space goal:\nreached by construction", ha="center", va="center",
                            transform=ax.transAxes, fontsize=7, color="0.4")  # fmt: skip
                    ax.set_axis_off()
                    continue
                for (method, recipe), g in pt.groupby(["method", "recipe"], sort=True):
                    est = [e for e in g[col]]
                    x = g["minutes"].to_numpy()
                    y = np.array([e.value for e in est], dtype=float)
                    lo = np.array([e.lo for e in est], dtype=float)
                    hi = np.array([e.hi for e in est], dtype=float)
                    many = len(x) > 1
                    ax.errorbar(
                        x, y, yerr=[np.nan_to_num(y - lo), np.nan_to_num(hi - y)], color=colors[recipe],
                        marker="o", ms=3.5, lw=1.2 if many else 0, capsize=2, elinewidth=0.7,
                        label=f"{method_label(method)}: {recipe}" if r == 0 and c == 0 else None,
                    )  # fmt: skip
                    for xi, yi, s in zip(x, y, g["steps"]):
                        if np.isfinite(yi):
                            ax.annotate(
                                f"{s // 1000}k", (xi, yi), textcoords="offset points", xytext=(3, -8), fontsize=6
                            )
                if col in ("success", "fraction_valid"):
                    ax.set_ylim(-3, 103)
                ax.set_xscale("log")  # budgets double: a log axis spaces them evenly
                plain_log_ticks(ax.xaxis)
                ax.set_xlabel("training wall time [min] (log)")
                ax.set_ylabel(label)
                ax.set_title(f"{short_task(task)}\n{label}", fontsize=8.5)
                ax.grid(lw=0.3, color="0.88")
                ax.set_axisbelow(True)
        fig.legend(loc="outside lower center", ncol=1, frameon=False, fontsize=7)
    return fig


def recipes_table(d: pd.DataFrame) -> str:
    """Markdown: every (task, method, recipe, budget) with its cost and its metrics."""
    if not has_curves(d):
        return "This run varies no `training.steps`: no learning curves."
    pts = curve_points(d)
    head = ["task", "method", "recipe", "steps", "train [min]", "contexts", "success [%]", "fraction valid [%]"]
    head += ["Vendi"]
    goal = [g for g in GOAL if pts[g[0]].notna().any()]  # only for end-effector-goal tasks
    head += [label for _, label, _, _ in goal]
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join(["---"] * 3 + ["---:"] * (len(head) - 3)) + " |"]
    for _, p in pts.iterrows():
        cells = [short_task(p["task"]), method_label(p["method"]), p["recipe"], str(p["steps"]), f"{p['minutes']:.1f}"]
        cells += [str(p["contexts"])]
        cells += [fmt_estimate(p[c], "{:.1f}") for c in ("success", "fraction_valid")]
        cells += [fmt_estimate(p["vendi"], "{:.2f}")]
        cells += [fmt_estimate(p[c], f) if isinstance(p[c], Estimate) else "–" for c, _, _, f in goal]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


__all__ = ["TRAINING_NOTE", "curve_points", "has_curves", "learning_curve_figure", "recipes_table"]
