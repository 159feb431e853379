"""Shared look of the report's figures: method and parametrization colours, the mean cross, legends, the caption
and the note of which cells a figure shows.

Methods keep one colour in every figure (colour-blind safe, none orange or black: those mean valid / invalid in
the scene figures); the cross marks the mean, as in the paper.
"""

from __future__ import annotations

import textwrap

from matplotlib.figure import Figure
from matplotlib.patches import Patch

from mpd.viz.report_data import EXTRA, TRAIN, describe_slice, method_label
from mpd.viz.scene import style

METHOD_COLORS = {
    "gp-cost": "#8C8C8C",
    "cvae": "#56B4E9",
    "cvae-cost": "#0072B2",
    "dprior": "#CC79A7",
    "dprior-cost": "#882255",
    "mpd": "#009E73",
    "rrtconnect-cost": "#332288",
}
SPARE_COLORS = ("#44AA99", "#999933", "#117733", "#AA4499", "#6699CC")
PARAM_COLORS = {"bspline": "#0072B2", "waypoints": "#CC79A7"}
PARAM_LABELS = {"bspline": "B-spline", "waypoints": "waypoints"}
SCENES = (TRAIN, EXTRA)


def method_color(method: str) -> str:
    if method in METHOD_COLORS:
        return METHOD_COLORS[method]
    return SPARE_COLORS[sum(map(ord, method)) % len(SPARE_COLORS)]  # stable across runs, unlike hash()


def palette(methods) -> dict[str, str]:
    return {method_label(m): method_color(m) for m in methods}


def add_caption(fig: Figure, caption: str) -> None:
    """Small grey lines under everything else in the figure: the caption (spec, hash, commit) and the slice of the
    run the figure shows. Placed after a layout pass, below the lowest artist, so that nothing overlaps."""
    from matplotlib.transforms import Bbox

    lines = [t for t in (caption, getattr(fig, "_mpd_note", "")) if t]
    if not lines:
        return
    with style():  # the layout must see the fonts the saved file will have
        engine = fig.get_layout_engine()
        if engine is not None:
            engine.execute(fig)  # the layout alone: a full draw costs as much again
        # A figure legend is anchored to the figure's box; saving with bbox_inches="tight" swaps that box for
        # the tight one, which reaches down to the caption, and the legend would follow it onto the caption.
        # So: freeze the layout just computed (the constrained layout would undo what follows) and anchor each
        # legend to the same box given in figure coordinates, which the tight box keeps in place.
        fig.set_layout_engine("none")
        for leg in fig.legends:
            leg.set_bbox_to_anchor((0, 0, 1, 1), transform=fig.transFigure)
        bb = fig.get_tightbbox()  # inches, may extend past the figure's own box
        w, h = fig.get_size_inches()
        text = fig.text(
            max(bb.x0, 0.0) / w,
            (bb.y0 - 0.04) / h,
            "\n".join(lines),
            ha="left",
            va="top",
            fontsize=6.5,
            color="0.4",
            linespacing=1.3,
        )
        renderer = fig._get_renderer()
        tb = text.get_window_extent(renderer).transformed(fig.dpi_scale_trans.inverted())
        if tb.width > bb.width:  # a narrow figure: wrap the caption to the figure's width instead of widening it
            chars = max(len(t) for t in lines)
            width = max(30, int(chars * bb.width / tb.width))
            text.set_text("\n".join(textwrap.fill(t, width, break_on_hyphens=False) for t in lines))
            tb = text.get_window_extent(renderer).transformed(fig.dpi_scale_trans.inverted())
    # the saved area, caption included: saving with it skips the extra draw that bbox_inches="tight" costs
    fig._mpd_bbox = Bbox.union([bb, tb]).padded(0.05)


def mean_cross(ax, xs, ys) -> None:
    ax.scatter(xs, ys, marker="x", s=34, linewidths=2.6, color="white", zorder=6)
    ax.scatter(xs, ys, marker="x", s=28, linewidths=1.3, color="black", zorder=7)


def method_legend(fig: Figure, methods, **kw) -> None:
    handles = [Patch(facecolor=method_color(m), edgecolor="none", label=method_label(m)) for m in methods]
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 7), frameon=False, **kw)


def set_note(fig: Figure, chosen: dict) -> None:
    """Remember which setting of the variant axes the figure shows; :func:`add_caption` writes it."""
    if chosen:
        fig._mpd_note = f"cells with {describe_slice(chosen)}"


def plain_log_ticks(axis) -> None:
    """Log-scale ticks at 1, 2, 5 x 10^k written as 0.5, 1, 20 rather than 5x10^-1: easier to read at a glance,
    and a range within one decade still gets labels."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())
