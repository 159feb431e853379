"""Figures of the paper's ablations and comparisons, each made only when the run has its cells: RRTConnect+Cost
vs MPD (Fig. 10), B-spline vs waypoints (smoothness KDE, sampling time), and sweeps over the scene's rotation
and the batch size."""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from mpd.viz.report_data import EXTRA, TRAIN, main_slice, method_label, method_order, short_task, task_order
from mpd.viz.report_style import (
    PARAM_COLORS,
    PARAM_LABELS,
    SCENES,
    SPARE_COLORS,
    method_color,
    palette,
    plain_log_ticks,
    set_note,
)
from mpd.viz.scene import style


# ------------------------------------------------------------------------- Fig. 10: RRTConnect+Cost vs MPD
def _rrtc_groups(d: pd.DataFrame):
    out = []
    for (task, scene), g in d.groupby(["task", "scene"], sort=False):
        # the paper's comparison: one RRTConnect path against MPD with growing batches
        if {"rrtconnect-cost", "mpd"} <= set(g["method"]) and g.loc[g["method"] == "mpd", "n_samples"].nunique() > 1:
            out.append((task, scene, g[g["method"].isin(["rrtconnect-cost", "mpd"])]))
    order = {t: i for i, t in enumerate(task_order(d["task"].unique()))}
    return sorted(out, key=lambda t: (order[t[0]], SCENES.index(t[1]) if t[1] in SCENES else 2))


def rrtconnect_figure(d: pd.DataFrame) -> Figure | None:
    """The paper's Fig. 10: RRTConnect+Cost (one path) vs MPD with growing batches: time and success by batch
    size (left), the shortest valid path's length (right)."""
    d, chosen = main_slice(d, free=("n_samples",))
    groups = _rrtc_groups(d)
    if not groups or "best_path_length" not in d.columns:
        return None
    with style():
        fig = Figure(figsize=(7.2, 2.6 * len(groups) + 0.3), layout="constrained")
        axes = fig.subplots(len(groups), 2, squeeze=False, gridspec_kw={"width_ratios": [1.25, 1]})
        for r, (task, scene, g) in enumerate(groups):
            cats = []
            for m in ("rrtconnect-cost", "mpd"):
                for n in sorted(g.loc[g["method"] == m, "n_samples"].unique()):
                    name = "RRTC+Cost" if m == "rrtconnect-cost" else "MPD"
                    cats.append((f"{name}\nB = {int(n)}", m, g[(g["method"] == m) & (g["n_samples"] == n)]))
            ax, ax2 = axes[r, 0], axes[r, 0].twinx()
            x = np.arange(len(cats))
            t = [c[2]["time_total"].astype(float) for c in cats]
            ax.bar(
                x,
                [v.mean() for v in t],
                yerr=[v.std(ddof=1) if len(v) > 1 else 0 for v in t],
                width=0.6,
                color=[method_color(c[1]) for c in cats],
                alpha=0.75,
                capsize=2,
                error_kw={"lw": 0.8},
            )
            s = [100 * c[2]["success"].astype(float).mean() for c in cats]
            ax2.plot(x, s, color="0.15", marker="o", ms=4, lw=1.0)
            for xi, si in zip(x, s):
                ax2.annotate(f"{si:.0f}%", (xi, si), textcoords="offset points", xytext=(0, 5), ha="center", fontsize=7)
            ax2.set_ylim(0, 112)
            ax2.set_ylabel("success [%] (line)")
            ax.set_ylim(0, 1.15 * max(v.mean() + (v.std(ddof=1) if len(v) > 1 else 0) for v in t))
            ax.set_ylabel("time per context [s] (bars)")
            ax.set_xticks(x, [c[0] for c in cats], fontsize=7)
            ax.set_title(f"{short_task(task)}, {scene}: time and success", fontsize=8.5)
            ax.grid(axis="y", lw=0.3, color="0.88")
            ax.set_axisbelow(True)
            bx = axes[r, 1]
            data = [c[2]["best_path_length"].astype(float).dropna().to_numpy() for c in cats]
            keep = [i for i, v in enumerate(data) if len(v)]
            if keep:
                bp = bx.boxplot(
                    [data[i] for i in keep],
                    positions=list(keep),
                    widths=0.55,
                    patch_artist=True,
                    showfliers=False,
                    medianprops={"color": "black", "lw": 1.0},
                )
                for i, patch in zip(keep, bp["boxes"]):
                    patch.set(facecolor=method_color(cats[i][1]), alpha=0.55, edgecolor="0.2", lw=0.7)
                rng = np.random.default_rng(0)  # fixed jitter: the same table gives the same figure
                for i in keep:
                    bx.scatter(
                        i + rng.uniform(-0.15, 0.15, len(data[i])),
                        data[i],
                        s=4,
                        color="0.25",
                        lw=0,
                        alpha=0.6,
                        zorder=3,
                    )
            bx.set_xticks(x, [c[0] for c in cats], fontsize=7)
            bx.set_xlim(-0.6, len(cats) - 0.4)
            bx.set_ylabel("shortest path length (joint space)")
            bx.set_title("shortest valid path", fontsize=8.5)
            bx.grid(axis="y", lw=0.3, color="0.88")
            bx.set_axisbelow(True)
        set_note(fig, chosen)
    return fig


# -------------------------------------------------------------------------- B-spline vs waypoints
def _param_pairs(d: pd.DataFrame) -> tuple[pd.DataFrame, dict]:
    """Rows of (task, method) that ran both parametrizations; MPD where it did, and the extra-objects scene where
    present (the paper's setting for its smoothness KDE)."""
    d, chosen = main_slice(d, free=("parametrization",))
    keep = []
    for _, g in d.groupby("task", sort=False):
        both = [m for m, gm in g.groupby("method") if gm["parametrization"].nunique() > 1]
        if not both:
            continue
        m = "mpd" if "mpd" in both else method_order(both)[0]
        gm = g[g["method"] == m]
        scene = EXTRA if (gm["scene"] == EXTRA).any() else TRAIN
        keep.append(gm[gm["scene"] == scene])
    return (pd.concat(keep) if keep else d.iloc[:0]), chosen


def smoothness_figure(d: pd.DataFrame) -> Figure | None:
    """The paper's smoothness KDE ("bspline_vs_waypoints_kde"): the density over contexts of the smoothness (sum of
    acceleration norms; lower is smoother), B-spline vs waypoints, one panel per task."""
    import seaborn as sns

    g, chosen = _param_pairs(d)
    if g.empty or "smoothness" not in g.columns or g["smoothness"].notna().sum() < 2:
        return None
    tasks = task_order(g["task"].unique())
    ncol = min(3, len(tasks))
    nrow = -(-len(tasks) // ncol)
    params = sorted(g["parametrization"].unique(), key=lambda p: (p != "bspline", p))
    pal = {p: PARAM_COLORS.get(p, SPARE_COLORS[i % len(SPARE_COLORS)]) for i, p in enumerate(params)}
    with style():
        fig = Figure(figsize=(2.7 * ncol + 0.3, 2.2 * nrow + 0.6), layout="constrained")
        axes = fig.subplots(nrow, ncol, squeeze=False)
        for ax, task in zip(axes.flat, tasks):
            gt = g[(g["task"] == task) & (g["smoothness"] > 0)].dropna(subset=["smoothness"])
            for p in params:
                v = gt.loc[gt["parametrization"] == p, "smoothness"].astype(float)
                if len(v) >= 2 and v.nunique() > 1:
                    sns.kdeplot(
                        x=v, ax=ax, log_scale=True, fill=True, alpha=0.3, color=pal[p], lw=1.2, warn_singular=False
                    )
                elif len(v):  # too few distinct values for a density: a rug
                    ax.set_xscale("log")
                    ax.plot(v, np.zeros(len(v)), "|", color=pal[p], ms=12)
            method = gt["method"].iloc[0] if len(gt) else ""
            scene = gt["scene"].iloc[0] if len(gt) else ""
            ax.set_title(f"{short_task(task)}\n{method_label(method)}, {scene}", fontsize=8)
            plain_log_ticks(ax.xaxis)
            ax.set_xlabel("smoothness (lower is smoother)")
            ax.set_ylabel("density")
            ax.grid(lw=0.3, color="0.9")
        for ax in list(axes.flat)[len(tasks) :]:
            ax.set_visible(False)
        handles = [Patch(facecolor=pal[p], alpha=0.5, edgecolor=pal[p], label=PARAM_LABELS.get(p, p)) for p in params]
        fig.legend(handles=handles, loc="outside lower center", ncol=len(params), frameon=False)
        set_note(fig, chosen)
    return fig


def parametrization_time_figure(d: pd.DataFrame) -> Figure | None:
    """Sampling time (denoising network and interpolation) with B-splines vs waypoints, per task (the paper's
    "bspline_vs_waypoints_computation_time" compares the same quantity)."""
    import seaborn as sns

    g, chosen = _param_pairs(d)
    col = "time_sampling" if "time_sampling" in g.columns and g["time_sampling"].notna().any() else "time_total"
    if g.empty or col not in g.columns or g[col].notna().sum() == 0:
        return None
    tasks = task_order(g["task"].unique())
    params = sorted(g["parametrization"].unique(), key=lambda p: (p != "bspline", p))
    pal = {p: PARAM_COLORS.get(p, SPARE_COLORS[i % len(SPARE_COLORS)]) for i, p in enumerate(params)}
    x = g.assign(_task=[short_task(t) for t in g["task"]], _y=g[col].astype(float))
    with style():
        fig = Figure(figsize=(1.2 * len(tasks) + 2.4, 2.8), layout="constrained")
        ax = fig.subplots()
        sns.barplot(
            data=x,
            x="_task",
            y="_y",
            hue="parametrization",
            order=[short_task(t) for t in tasks],
            hue_order=params,
            palette=pal,
            errorbar="sd",
            capsize=0.15,
            err_kws={"linewidth": 0.8},
            ax=ax,
            alpha=0.85,
        )
        ax.set_xlabel("")
        ax.set_ylabel(f"{'sampling' if col == 'time_sampling' else 'total'} time per context [s]")
        ax.tick_params(axis="x", labelsize=7)
        ax.grid(axis="y", lw=0.3, color="0.88")
        ax.set_axisbelow(True)
        handles, labels = ax.get_legend_handles_labels()
        ax.legend(handles, [PARAM_LABELS.get(p, p) for p in labels], title="", frameon=False, fontsize=7)
        ax.set_title("sampling time, B-spline vs waypoints\n(mean ± std over contexts)", fontsize=8.5)
        set_note(fig, chosen)
    return fig


# -------------------------------------------------------------------- rotation and batch-size sweeps
def _sweep(d: pd.DataFrame, axis: str, metrics, xlabel: str, logx: bool, title: str) -> Figure | None:
    import seaborn as sns

    d, chosen = main_slice(d, free=(axis,))
    rows = []
    for task in task_order(d["task"].unique()):
        for scene in SCENES:
            g = d[(d["task"] == task) & (d["scene"] == scene)]
            sweeping = [m for m, gm in g.groupby("method") if gm[axis].nunique() > 1]
            if sweeping:  # a method run at one value only would be a lone point: left out
                rows.append((task, scene, g[g["method"].isin(sweeping)]))
    metrics = [m for m in metrics if m[0] in d.columns]
    if not rows or not metrics:
        return None
    methods = method_order(pd.concat([g for *_, g in rows])["method"].unique())
    with style():
        fig = Figure(figsize=(2.9 * len(metrics) + 0.3, 2.3 * len(rows) + 0.6), layout="constrained")
        axes = fig.subplots(len(rows), len(metrics), squeeze=False)
        for r, (task, scene, g) in enumerate(rows):
            x = g.copy()
            for c, (col, label, scale, logy) in enumerate(metrics):
                ax = axes[r, c]
                x["_y"] = x[col].astype(float) * scale
                x["_x"] = x[axis].astype(float)
                sns.lineplot(
                    data=x,
                    x="_x",
                    y="_y",
                    hue="label",
                    hue_order=[method_label(m) for m in methods],
                    palette=palette(methods),
                    marker="o",
                    markersize=4.5,
                    errorbar="se",
                    err_style="bars",
                    err_kws={"capsize": 2, "lw": 0.8},
                    ax=ax,
                    legend=False,
                    lw=1.2,
                )
                if logx:
                    ax.set_xscale("log")
                    ax.set_xticks(sorted(x["_x"].unique()), [f"{v:g}" for v in sorted(x["_x"].unique())])
                    ax.minorticks_off()
                else:
                    ax.set_xticks(sorted(x["_x"].unique()))
                pos = x["_y"][x["_y"] > 0]
                if logy and len(pos) and pos.max() > 10 * pos.min():  # log only when it spans a decade
                    ax.set_yscale("log")
                    plain_log_ticks(ax.yaxis)
                if col in ("success", "fraction_valid"):
                    ax.set_ylim(-3, 103)
                ax.set_xlabel(xlabel)
                ax.set_ylabel(label)
                ax.set_title(f"{short_task(task)}, {scene}", fontsize=8)
                ax.grid(lw=0.3, color="0.9")
        handles = [
            Line2D([], [], color=method_color(m), marker="o", ms=4.5, lw=1.2, label=method_label(m)) for m in methods
        ]
        fig.legend(handles=handles, loc="outside lower center", ncol=min(7, len(handles)), frameon=False)
        fig.suptitle(title, fontsize=9)
        set_note(fig, chosen)
    return fig


def rotation_figure(d: pd.DataFrame) -> Figure | None:
    """Success and fraction valid against the scene's rotation about the base (mean ± s.e. over contexts)."""
    return _sweep(
        d,
        "rotation_deg",
        [("success", "success [%]", 100.0, False), ("fraction_valid", "fraction valid [%]", 100.0, False)],
        "rotation of the obstacles [°]",
        False,
        "generalisation to a rotated scene",
    )


def batch_size_figure(d: pd.DataFrame) -> Figure | None:
    """Planning time and success against the number of trajectories sampled per context."""
    return _sweep(
        d,
        "n_samples",
        [("time_total", "time per context [s]", 1.0, True), ("success", "success [%]", 100.0, False)],
        "batch size (trajectories per context)",
        True,
        "time and success vs batch size",
    )
