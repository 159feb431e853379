"""The report's figures, from the results table alone (seaborn-style plots on matplotlib, no pyplot).

Each figure function takes the prepared table (:func:`mpd.viz.report_data.prepare`) and returns a
:class:`~matplotlib.figure.Figure`, or None when the run lacks the cells it needs (the report then skips it).
Here: the paper's Fig. 6 (metrics per method, swarms) and Fig. 9 (MPD time breakdown), and the registry of every
figure kind; the ablations are in :mod:`mpd.viz.report_ablations`, the shared look in
:mod:`mpd.viz.report_style`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from mpd import stats
from mpd.viz.report_ablations import (
    batch_size_figure,
    parametrization_time_figure,
    rotation_figure,
    rrtconnect_figure,
    smoothness_figure,
)
from mpd.viz.report_data import ee_goal, main_slice, method_label, method_order, short_task, task_order
from mpd.viz.report_style import (
    SCENES,
    add_caption,
    mean_cross,
    method_legend,
    palette,
    set_note,
)
from mpd.viz.report_tables import cost_columns, gradient_calls
from mpd.viz.report_training import learning_curve_figure
from mpd.viz.scene import style

# ------------------------------------------------------------------------------------- Fig. 6: swarm plots
SWARM_METRICS = (
    ("success", "success\n[%]", 100.0),
    ("fraction_valid", "fraction valid\n[%]", 100.0),
    ("vendi", "diversity\n(Vendi)", 1.0),
    ("ee_pos_error", "EE position\nerror [cm]", 100.0),
    ("ee_ori_error_deg", "EE orientation\nerror [°]", 1.0),
)


def beeswarm(y: np.ndarray, diameter: float, max_half_width: float) -> np.ndarray:
    """Horizontal offsets (same unit as ``y`` and ``diameter``) that keep points of one category from overlapping:
    each point, from the lowest up, takes the free position nearest the centre line among those touching an
    already placed neighbour; past ``max_half_width`` it overlaps at the least crowded allowed position.

    Computed once, unlike seaborn's swarm, which places its points again at every draw (the report draws each
    figure three times); deterministic for a given table."""
    y = np.asarray(y, dtype=float)
    x = np.zeros(len(y))
    done: list[int] = []
    for i in np.argsort(y, kind="stable"):
        if done:
            px, py = x[done], y[done]
            dy = y[i] - py
            near = np.abs(dy) < diameter
            px, dy = px[near], dy[near]
            cands = [0.0]
            if len(px):
                half = np.sqrt(np.maximum(diameter**2 - dy**2, 0.0))
                cands = np.concatenate([[0.0], px + half, px - half])
            cands = np.asarray(cands)
            cands = cands[np.argsort(np.abs(cands), kind="stable")]
            ok = [c for c in cands if abs(c) <= max_half_width and np.all((c - px) ** 2 + dy**2 >= diameter**2 - 1e-12)]
            if ok:
                x[i] = ok[0]
            elif len(px):  # no room: the allowed position farthest from its neighbours
                grid = np.linspace(-max_half_width, max_half_width, 21)
                gap = np.min((grid[:, None] - px[None]) ** 2 + dy[None] ** 2, axis=1)
                x[i] = grid[int(np.argmax(gap))]
        done.append(i)
    return x


def success_yerr(mean: float, lo: float, hi: float) -> list[list[float]]:
    """Matplotlib's asymmetric error bar (in %) of a rate and its interval: never negative (at a rate of 0 or 1
    the Wilson bound equals the rate up to rounding, which can land on the wrong side), 0 where undefined."""
    below, above = 100 * (mean - lo), 100 * (hi - mean)
    return [[max(float(np.nan_to_num(below)), 0.0)], [max(float(np.nan_to_num(above)), 0.0)]]


def _swarm_panel(ax, g: pd.DataFrame, col: str, scale: float, methods: list[str], ylim, size_in) -> None:
    """One panel of Fig. 6: success as bars with Wilson's 95% interval, every other metric as a swarm per method
    with the 95% bootstrap interval of its mean; the cross at the mean. ``ylim`` fixes the y range first, so the
    swarm can be laid out in inches (``size_in``: the panel's approximate width and height)."""
    pal = palette(methods)
    x = g.assign(_y=pd.to_numeric(g[col], errors="coerce") * scale)
    ax.set_xlim(-0.6, len(methods) - 0.4)
    if col == "success":
        # a success is 0 or 1 per context: a swarm of two stacks says less than the rate and its interval
        for i, m in enumerate(methods):
            v = x.loc[x["method"] == m, "_y"].dropna() / 100.0
            if v.empty:
                continue
            lo, hi = stats.wilson(v.sum(), len(v))
            c = pal[method_label(m)]
            ax.bar(i, 100 * v.mean(), width=0.7, color=c, alpha=0.45, edgecolor=c)
            ax.errorbar(
                i,
                100 * v.mean(),
                yerr=success_yerr(v.mean(), lo, hi),
                color="0.2",
                lw=0.8,
                capsize=1.5,
            )
            mean_cross(ax, [i], [100 * v.mean()])
        ax.set_ylim(0, 104)
        return
    ax.set_ylim(*ylim)
    n = int(x.groupby("method")["_y"].count().max()) if len(x) else 0
    dot = 2.6 if n <= 40 else 2.0 if n <= 120 else 1.4  # points
    w_in, h_in = size_in
    in_per_x = w_in / (len(methods) + 0.2)
    in_per_y = h_in / max(ylim[1] - ylim[0], 1e-12)
    for i, m in enumerate(methods):
        v = x.loc[x["method"] == m, "_y"].dropna().to_numpy()
        if not len(v):
            continue
        off = beeswarm(v * in_per_y, dot / 72 * 1.05, 0.42 * in_per_x) / in_per_x
        ax.scatter(i + off, v, s=dot**2, color=pal[method_label(m)], lw=0, alpha=0.85, zorder=3)
        ci = stats.bootstrap(v)
        if np.isfinite(ci.lo):  # the 95 % interval of the mean (bootstrap over contexts); none with one context
            yerr = [[abs(ci.value - ci.lo)], [abs(ci.hi - ci.value)]]
            ax.errorbar(i, ci.value, yerr=yerr, color="0.1", lw=1.1, capsize=2.2, capthick=1.1, zorder=5)
        mean_cross(ax, [i], [v.mean()])


def _limits(values: pd.Series) -> tuple[float, float]:
    v = pd.to_numeric(values, errors="coerce").dropna()
    if v.empty:
        return (0.0, 1.0)
    lo, hi = float(v.min()), float(v.max())
    pad = 0.06 * (hi - lo) if hi > lo else max(abs(hi) * 0.1, 1e-3)
    return lo - pad, hi + pad


def swarm_figure(d: pd.DataFrame) -> Figure | None:
    """The paper's Fig. 6: a block of columns per scene (training environment, extra objects), in each the columns
    success / fraction valid / diversity (/ EE position and orientation errors when a task has an end-effector
    goal); one row per task; one swarm per method, the cross at the mean. A metric keeps its y range across the
    two blocks, so the drop with extra objects reads directly."""
    from matplotlib.ticker import MaxNLocator

    d, chosen = main_slice(d)
    if d.empty:
        return None
    tasks = task_order(d["task"].unique())
    any_ee = any(ee_goal(d, t) for t in tasks)
    metrics = [m for m in SWARM_METRICS if m[0] in d.columns and (any_ee or not m[0].startswith("ee_"))]
    scenes = [s for s in SCENES if (d["scene"] == s).any()]
    methods = method_order(d["method"].unique())
    w = max(0.95, 0.17 * len(methods) + 0.45)
    row_h = 1.6
    size_in = (w - 0.45, row_h - 0.45)  # the axes inside a panel: without tick labels and titles (roughly)
    with style():
        fig = Figure(figsize=(w * len(metrics) * len(scenes) + 0.5, row_h * len(tasks) + 1.3), layout="constrained")
        subs = np.atleast_1d(fig.subfigures(1, len(scenes), wspace=0.03))
        for sub, scene in zip(subs, scenes):
            sub.suptitle(scene, fontsize=9, fontweight="bold")
            axes = sub.subplots(len(tasks), len(metrics), squeeze=False)
            for r, task in enumerate(tasks):
                gt = d[d["task"] == task]
                g = gt[gt["scene"] == scene]
                for c, (col, title, scale) in enumerate(metrics):
                    ax = axes[r, c]
                    msg = None
                    if col.startswith("ee_") and not ee_goal(d, task):
                        msg = "joint goal:\nno EE error"
                    elif g.empty:
                        msg = "not run"
                    if msg:
                        ax.text(
                            0.5, 0.5, msg, ha="center", va="center", fontsize=7, color="0.45", transform=ax.transAxes
                        )
                        ax.set_xticks([])
                        ax.set_yticks([])
                    else:
                        # one y range per task and metric over both scenes
                        ylim = _limits(pd.to_numeric(gt[col], errors="coerce") * scale)
                        _swarm_panel(ax, g, col, scale, methods, ylim, size_in)
                        ax.set_xticks(range(len(methods)))
                        ax.yaxis.set_major_locator(MaxNLocator(4))
                    ax.grid(axis="y", lw=0.3, color="0.88")
                    ax.set_axisbelow(True)
                    ax.tick_params(axis="y", labelsize=6.5, pad=1)
                    if r == len(tasks) - 1 and len(ax.get_xticks()):
                        ax.set_xticklabels([method_label(m) for m in methods], rotation=90, fontsize=6.5)
                    else:
                        ax.tick_params(labelbottom=False)
                    if r == 0:
                        ax.set_title(title, fontsize=7.5)
                    if c == 0 and scene == scenes[0]:  # the scenes share rows: a label in the gap would overlap
                        ax.set_ylabel(short_task(task).replace(" / ", "\n"), fontsize=7.5, fontweight="bold")
        method_legend(fig, methods)
        set_note(fig, chosen)
    return fig


# ---------------------------------------------------------------------------------- Fig. 9: MPD timings
_PARTS = (
    ("network", "denoising network", "#0072B2"),
    ("sampling_rest", "rest of sampling", "#56B4E9"),
    ("cost_gradient", "cost gradients", "#009E73"),
    ("rest", "other", "#BBBBBB"),
)
_COST_COLORS = ("#332288", "#88CCEE", "#44AA99", "#117733", "#999933", "#DDCC77", "#CC6677", "#882255", "#AA4499")


def timing_figure(d: pd.DataFrame) -> Figure | None:
    """The paper's Fig. 9 for every MPD cell: total time split into the denoising network, the rest of sampling
    and the cost gradients (left), and one gradient step split by cost (right)."""
    d, chosen = main_slice(d)
    d = d[d["method"] == "mpd"]
    need = ("time_total", "time_sampling", "time_network", "time_cost_gradient")
    if d.empty or not all(c in d.columns and d[c].notna().any() for c in need):
        return None
    rows = []
    for task in task_order(d["task"].unique()):
        for scene in SCENES:
            g = d[(d["task"] == task) & (d["scene"] == scene)]
            if g.empty:
                continue
            m = {c: g[c].astype(float).mean() for c in need}
            calls = gradient_calls(g)
            n_calls = float(calls.mean()) if calls is not None and calls.mean() > 0 else np.nan
            rows.append(
                {
                    "name": f"{short_task(task)}\n{scene}",
                    "network": m["time_network"],
                    "sampling_rest": max(m["time_sampling"] - m["time_network"], 0.0),
                    "cost_gradient": m["time_cost_gradient"],
                    "rest": max(m["time_total"] - m["time_sampling"] - m["time_cost_gradient"], 0.0),
                    "total": m["time_total"],
                    "total_sd": g["time_total"].astype(float).std(ddof=1) if len(g) > 1 else 0.0,
                    "costs": {
                        c.removeprefix("time_cost_"): 1000 * g[c].astype(float).mean() / n_calls
                        for c in cost_columns(g)
                    },
                    "calls": n_calls,
                }
            )
    costs = sorted({k for r in rows for k in r["costs"]})
    with style():
        fig = Figure(figsize=(8.6, 0.55 * len(rows) + 1.7), layout="constrained")
        ax0, ax1 = fig.subplots(1, 2, sharey=True, gridspec_kw={"width_ratios": [1.15, 1]})
        y = np.arange(len(rows))[::-1]
        left = np.zeros(len(rows))
        for key, label, color in _PARTS:
            v = np.array([r[key] for r in rows])
            ax0.barh(y, v, left=left, height=0.6, color=color, label=label, edgecolor="white", linewidth=0.5)
            left += v
        for yi, r in zip(y, rows):
            ax0.text(r["total"], yi, f"  {r['total']:.3g} s", va="center", fontsize=7)
        ax0.set_xlim(0, 1.22 * max(r["total"] for r in rows))
        ax0.set_yticks(y, [r["name"] for r in rows], fontsize=7)
        ax0.set_xlabel("time per context [s] (mean)", fontsize=8)
        ax0.set_title("MPD: total inference time", fontsize=8.5)
        ax0.legend(
            loc="upper center",
            bbox_to_anchor=(0.5, -0.16 if len(rows) < 4 else -0.08),
            ncol=2,
            frameon=False,
            fontsize=7,
        )
        left = np.zeros(len(rows))
        for i, c in enumerate(costs):
            v = np.array([r["costs"].get(c, 0.0) for r in rows])
            v = np.nan_to_num(v)
            ax1.barh(
                y,
                v,
                left=left,
                height=0.6,
                color=_COST_COLORS[i % len(_COST_COLORS)],
                label=c,
                edgecolor="white",
                linewidth=0.5,
            )
            left += v
        for yi, r, tot in zip(y, rows, left):
            if np.isfinite(r["calls"]):
                ax1.text(tot, yi, f"  {tot:.3g} ms × {r['calls']:.0f} steps", va="center", fontsize=7)
        if left.max() > 0:
            ax1.set_xlim(0, 1.85 * left.max())  # room for the "ms x steps" label
        ax1.set_xlabel("time per gradient step [ms] (mean)", fontsize=8)
        ax1.set_title("one cost-gradient step, by cost", fontsize=8.5)
        ax1.legend(
            loc="upper center",
            bbox_to_anchor=(0.5, -0.16 if len(rows) < 4 else -0.08),
            ncol=min(4, max(1, len(costs))),
            frameon=False,
            fontsize=7,
        )
        for ax in (ax0, ax1):
            ax.grid(axis="x", lw=0.3, color="0.88")
            ax.set_axisbelow(True)
        set_note(fig, chosen)
    return fig


# ---------------------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class FigureKind:
    name: str  # file stem under report/figures/
    title: str
    make: Callable[[pd.DataFrame], Figure | None]
    needs: str  # what the run must have; said when the figure is skipped


FIGURES = (
    FigureKind(
        "swarm", "Metrics per method, training environment and extra objects (Fig. 6)", swarm_figure, "any cell"
    ),
    FigureKind("timing", "MPD computation time breakdown (Fig. 9)", timing_figure, "MPD cells with timings"),
    FigureKind(
        "rrtconnect_vs_mpd",
        "RRTConnect+Cost vs MPD (Fig. 10)",
        rrtconnect_figure,
        "RRTConnect+Cost and MPD at several batch sizes on the same task and scene",
    ),
    FigureKind(
        "smoothness_kde",
        "Smoothness KDE, B-spline vs waypoints",
        smoothness_figure,
        "one method run with both parametrizations",
    ),
    FigureKind(
        "parametrization_time",
        "Sampling time, B-spline vs waypoints",
        parametrization_time_figure,
        "one method run with both parametrizations",
    ),
    FigureKind(
        "rotation", "Success and fraction valid vs scene rotation", rotation_figure, "cells at several rotations"
    ),
    FigureKind(
        "batch_size", "Time and success vs batch size", batch_size_figure, "a method run with several batch sizes"
    ),
    FigureKind(
        "learning_curves",
        "Prior quality vs training minutes, one line per recipe",
        learning_curve_figure,
        "cells at several training.steps",
    ),
)


__all__ = ["FIGURES", "FigureKind", "add_caption", "swarm_figure", "timing_figure"]
