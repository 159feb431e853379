"""Static figures of task scenes, robots and trajectories (matplotlib; no pyplot, so no global backend state).

Conventions of the paper's figures: valid trajectories orange, invalid black; extra (unseen) objects red;
joint trajectories against time with dashed joint limits. The other colours are from the Okabe-Ito palette,
which stays distinguishable under the common colour-vision deficiencies.

Every ``*_figure`` function returns a :class:`matplotlib.figure.Figure` and, given ``out``, writes it as PNG
(and as PDF too when ``out`` ends with ``.pdf``).
"""

from __future__ import annotations

import contextlib
import functools
import os
import weakref
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib import patches
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.gridspec import SubplotSpec
from matplotlib.lines import Line2D
from matplotlib.rcsetup import cycler
from matplotlib.ticker import FormatStrFormatter, MaxNLocator
from mpl_toolkits.mplot3d.art3d import Line3DCollection

from mpd.viz.mesh3d import add_polys, box_mesh, shade, sphere_mesh

# the paper's convention, then Okabe-Ito
VALID = "#E69F00"
INVALID = "#000000"
UNKNOWN = "#56B4E9"  # samples whose validity was not given
OBSTACLE = "#9a9a9a"
EXTRA = "#D55E00"
ROBOT = "#0072B2"
ROBOT_GOAL = "#009E73"
START = "#0072B2"
GOAL = "#009E73"
LIMIT = "#555555"

STYLE = {
    "font.size": 9,
    "axes.titlesize": 9.5,
    "axes.labelsize": 9,
    "legend.fontsize": 8,
    "xtick.labelsize": 7.5,
    "ytick.labelsize": 7.5,
    "axes.linewidth": 0.7,
    "axes.prop_cycle": cycler(color=["#0072B2", "#E69F00", "#009E73", "#CC79A7", "#56B4E9", "#D55E00", "#F0E442"]),
    "savefig.dpi": 200,
    "pdf.fonttype": 42,  # embed TrueType, so the text stays editable in a paper's PDF
    "ps.fonttype": 42,
}


@contextlib.contextmanager
def style() -> Iterator[None]:
    """The figure style; wraps both creation and saving, since matplotlib reads some settings at draw time."""
    import matplotlib

    with matplotlib.rc_context(STYLE):
        yield


# --------------------------------------------------------------------------------------- small helpers
def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _mask(valid, n: int) -> np.ndarray | None:
    if valid is None:
        return None
    v = valid.detach().cpu().numpy() if isinstance(valid, torch.Tensor) else np.asarray(valid)
    v = v.astype(bool).reshape(-1)
    if v.shape[0] != n:
        raise ValueError(f"valid has {v.shape[0]} entries for {n} trajectories")
    return v


def _is_3d(ax: Axes) -> bool:
    return getattr(ax, "name", "") == "3d"


def _is_point_mass(task) -> bool:
    return task.robot.n_spheres == 1 and task.robot.dof == task.dim


def _ee_positions(task, q: np.ndarray) -> np.ndarray:
    """(..., dof) joint positions -> (..., task_dim) end-effector positions (the point mass: itself)."""
    q = np.asarray(q, dtype=np.float64)
    if _is_point_mass(task):
        return q
    p, _ = task.robot.ee_pose(torch.as_tensor(q.reshape(-1, task.dof)))
    return p[:, : task.dim].numpy().reshape(*q.shape[:-1], task.dim)


def _lighten(color, amount: float) -> tuple[float, float, float, float]:
    r, g, b, a = to_rgba(color)
    return (r + (1 - r) * amount, g + (1 - g) * amount, b + (1 - b) * amount, a)


def save_figure(fig: Figure, out: str | Path) -> Path:
    """Write ``fig`` as PNG; when ``out`` ends with .pdf, as PDF and a PNG beside it (temp file + rename)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    targets = [out.with_suffix(".png")]
    if out.suffix.lower() == ".pdf":
        targets.append(out)
    with style():
        for path in targets:
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            fig.savefig(tmp, format=path.suffix[1:].lower(), bbox_inches="tight", pad_inches=0.04)
            os.replace(tmp, path)
    return out


def _finish(fig: Figure, out) -> Figure:
    if out is not None:
        save_figure(fig, out)
    return fig


def _box_corners_2d(centre, half_size, rotation) -> np.ndarray:
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float) * np.asarray(half_size)
    return np.asarray(centre) + local @ np.asarray(rotation).T


# ------------------------------------------------------------------------------------------------ axes
def new_task_axes(fig: Figure, task, spec: SubplotSpec | int = 111) -> Axes:
    """An axes suited to the task: 2-D with equal aspect, or 3-D with a view that shows the Panda's scene."""
    if task.dim == 3:
        # explicit zorders (scene 1, paths 3, robot skeleton 5, markers 6): mplot3d's computed order sorts
        # whole artists by mean depth, which hides paths and markers behind the one big scene collection
        ax = fig.add_subplot(spec, projection="3d", computed_zorder=False)
        ax.view_init(elev=24, azim=-35)
        _REACH[ax] = _reach_box(task.robot)
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_pane_color((0.97, 0.97, 0.97, 1.0))
            axis._axinfo["grid"].update(color=(0.85, 0.85, 0.85, 1.0), linewidth=0.4)
            axis.set_major_locator(MaxNLocator(4))
        ax.tick_params(pad=0, labelsize=6.5)
        ax.set_xlabel("x [m]", labelpad=-6, fontsize=8)
        ax.set_ylabel("y [m]", labelpad=-6, fontsize=8)
        ax.set_zlabel("z [m]", labelpad=-7, fontsize=8)
        return ax
    ax = fig.add_subplot(spec)
    for axis in (ax.xaxis, ax.yaxis):  # "-1", "0.5": short labels that do not collide between adjacent panels
        axis.set_major_formatter(FormatStrFormatter("%g"))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]", labelpad=1)
    return ax


_REACH: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


@functools.lru_cache(maxsize=8)
def _reach_box_cached(name: str) -> tuple[np.ndarray, np.ndarray]:
    from mpd.robots import get_robot

    robot = get_robot(name)
    q = robot.random_q(4096, torch.Generator().manual_seed(0))
    c = robot.sphere_centres(q).reshape(-1, robot.task_dim).numpy()
    r = robot.sphere_radii.max().item()
    return np.minimum(c.min(0) - r, 0.0), np.maximum(c.max(0) + r, 0.0)


def _reach_box(robot) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box around every collision sphere over random configurations (the robot's reach)."""
    return _reach_box_cached(robot.name)


def _view_box(ax: Axes, env) -> tuple[np.ndarray, np.ndarray]:
    """3-D view: the obstacles and the robot's reach, within the workspace (the Spheres3D workspace is 4 m
    wide, which would leave the scene a small cluster in the middle). Axes not made by new_task_axes show the
    workspace."""
    lo, hi = env.workspace
    if ax not in _REACH:
        return lo, hi
    blo, bhi = (np.array(v, dtype=float) for v in _REACH[ax])
    for p, _ in env.primitives:
        ext = p.radius if p.kind == "sphere" else np.abs(p.rotation) @ p.half_size
        blo, bhi = np.minimum(blo, p.centre - ext), np.maximum(bhi, p.centre + ext)
    pad = 0.03 * (bhi - blo)
    return np.maximum(blo - pad, lo), np.minimum(bhi + pad, hi)


def _set_limits(ax: Axes, env) -> None:
    lo, hi = env.workspace
    if _is_3d(ax):
        lo, hi = _view_box(ax, env)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(hi - lo), zoom=1.05)
    else:
        pad = 0.015 * (hi - lo)
        ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
        ax.set_ylim(lo[1] - pad[1], hi[1] + pad[1])
        ax.set_aspect("equal")


# -------------------------------------------------------------------------------------- public drawing
def draw_environment(ax: Axes, env, *, workspace: bool = True) -> None:
    """Obstacles grey, extra objects red; 2-D or 3-D after the axes' projection. ``workspace`` draws the frame
    of the workspace in 2-D; in 3-D the view is clipped to the workspace, so the axes' panes frame it."""
    if _is_3d(ax):
        verts, colors = [], []
        for p, extra in env.primitives:
            color = EXTRA if extra else OBSTACLE
            if p.kind == "sphere":
                v, n = sphere_mesh(p.centre, p.radius, 24, 12)
            else:
                v, n = box_mesh(p.centre, p.half_size, p.rotation)
            verts.append(v)
            colors.append(shade(color, n))
        if verts:
            add_polys(ax, np.concatenate(verts), np.concatenate(colors))
        _set_limits(ax, env)
        return
    frame = None
    if workspace:
        lo, hi = env.workspace
        frame = patches.Rectangle(lo[:2], *(hi - lo)[:2], fill=False, edgecolor="0.2", lw=1.0, zorder=1.5)
        ax.add_patch(frame)
        ax.spines[:].set_visible(False)  # the workspace rectangle is the frame; spines beside it look doubled
    for p, extra in env.primitives:
        fc = EXTRA if extra else OBSTACLE
        ec = EXTRA if extra else "#6f6f6f"
        if p.kind == "sphere":
            artist = patches.Circle(p.centre[:2], p.radius)
        else:
            artist = patches.Polygon(_box_corners_2d(p.centre[:2], p.half_size[:2], p.rotation[:2, :2]))
        artist.set(facecolor=fc, edgecolor=ec, linewidth=0.6, zorder=1)
        ax.add_patch(artist)
        if frame is not None:  # objects reaching past the workspace (NarrowPassage's walls) end at its frame
            artist.set_clip_path(frame)
    _set_limits(ax, env)


def draw_robot(ax: Axes, task, q, *, color=ROBOT, alpha: float = 1.0, spheres: bool = True) -> None:
    """The robot at one configuration q (dof,): a disc (point mass), links + joints + collision spheres
    (planar arms), or collision spheres + a polyline through the link frames (Panda, 3-D)."""
    robot = task.robot
    q = torch.as_tensor(_np(q).reshape(1, robot.dof))
    radii = robot.sphere_radii.numpy()
    if _is_point_mass(task):
        ax.add_patch(
            patches.Circle(
                q[0].numpy(),
                radii[0],
                facecolor=color,
                edgecolor="#1a1a1a",
                linewidth=0.5,
                alpha=alpha,
                zorder=4,
            )
        )
        return
    kin = robot.kinematics(q)
    centres = kin.points[0].numpy()
    frames = np.concatenate([np.zeros((1, 3)), kin.origins[0].numpy(), kin.ee_pos.numpy()])
    # consecutive joints can share an origin (Panda joints 1/2); a zero-length segment only adds a marker
    keep = np.r_[True, np.linalg.norm(np.diff(frames, axis=0), axis=1) > 1e-9]
    frames = frames[keep]
    if _is_3d(ax):
        if spheres:
            verts, colors = zip(*[sphere_mesh(c, r, 10, 6) for c, r in zip(centres, radii)])
            add_polys(ax, np.concatenate(verts), shade(color, np.concatenate(colors), alpha))
        ax.plot(*frames.T, color="#1a1a1a", linewidth=1.4, marker="o", markersize=2.2, alpha=alpha, zorder=5)
        return
    if spheres:
        for c, r in zip(centres, radii):
            ax.add_patch(
                patches.Circle(
                    c[:2],
                    r,
                    facecolor=_lighten(color, 0.55),
                    edgecolor=color,
                    linewidth=0.4,
                    alpha=alpha,
                    zorder=3,
                )
            )
    ax.plot(*frames[:, :2].T, color=color, linewidth=2.2, solid_capstyle="round", alpha=alpha, zorder=4)
    ax.plot(
        *frames[1:-1, :2].T,
        linestyle="none",
        marker="o",
        markersize=3.2,
        markerfacecolor="white",
        markeredgecolor=color,
        markeredgewidth=0.9,
        alpha=alpha,
        zorder=4.5,
    )
    ax.plot(0, 0, marker="s", markersize=5, color="#1a1a1a", alpha=alpha, zorder=4.6)


def draw_paths(
    ax: Axes,
    task,
    paths,
    valid=None,
    *,
    max_paths: int = 100,
    robot_start: bool = True,
    robot_goal: bool = True,
    robot_alpha: float = 0.9,
    goal_pos=None,
) -> dict[str, int]:
    """Dense joint paths (N, n, dof) in task space: valid orange, invalid black, start/goal markers; arms also
    drawn at the start (blue) and at the end of the first valid path (green). At most ``max_paths`` are drawn
    (evenly spaced). Returns {"total", "valid" (-1 when not given), "drawn"}."""
    q = _np(paths)
    if q.ndim == 2:
        q = q[None]
    n_all = q.shape[0]
    v = _mask(valid, n_all)
    counts = {"total": n_all, "valid": int(v.sum()) if v is not None else -1}  # of all, not of those drawn
    if n_all > max_paths:  # evenly spaced subset: deterministic, and keeps the valid/invalid mix
        idx = np.unique(np.linspace(0, n_all - 1, max_paths).round().astype(int))
        q, v = q[idx], (v[idx] if v is not None else None)
    x = _ee_positions(task, q)  # (N, n, task_dim)
    three = _is_3d(ax)
    lines = Line3DCollection if three else LineCollection
    groups = [(x, UNKNOWN, 0.8, 0.9)] if v is None else [(x[~v], INVALID, 0.55, 0.7), (x[v], VALID, 0.85, 1.0)]
    for seg, color, a, lw in groups:
        if len(seg):
            coll = lines(list(seg), colors=color, linewidths=lw, alpha=a, zorder=3)
            ax.add_collection3d(coll) if three else ax.add_collection(coll)
    arm = not _is_point_mass(task)
    end = int(np.argmax(v)) if v is not None and v.any() else 0
    if arm and robot_start:
        draw_robot(ax, task, q[0, 0], color=ROBOT, alpha=robot_alpha)
    if arm and robot_goal:
        draw_robot(ax, task, q[end, -1], color=ROBOT_GOAL, alpha=robot_alpha * 0.8)
    start = x[0, 0]
    goal = _np(goal_pos)[: task.dim] if goal_pos is not None else x[end, -1]
    kw = dict(linestyle="none", markeredgecolor="white", markeredgewidth=0.8, zorder=6)
    ax.plot(*start[:, None], marker="o", markersize=7, color=START, **kw)
    ax.plot(*goal[:, None], marker="*", markersize=11, color=GOAL, **kw)
    return {**counts, "drawn": len(q)}


def _legend(fig: Figure, counts: dict[str, int] | None, ncol: int = 4, **kw) -> None:
    handles = []
    if counts is not None and counts["valid"] >= 0:
        handles += [
            Line2D([], [], color=VALID, lw=1.5, label="valid"),
            Line2D([], [], color=INVALID, lw=1.2, label="invalid"),
        ]
    elif counts is not None:
        handles += [Line2D([], [], color=UNKNOWN, lw=1.5, label="samples")]
    handles += [
        Line2D(
            [],
            [],
            linestyle="none",
            marker="o",
            markersize=6,
            color=START,
            markeredgecolor="white",
            label="start",
        ),
        Line2D(
            [],
            [],
            linestyle="none",
            marker="*",
            markersize=9,
            color=GOAL,
            markeredgecolor="white",
            label="goal",
        ),
    ]
    fig.legend(
        handles=handles,
        loc="outside lower center",
        ncol=ncol,
        frameon=False,
        handlelength=1.6,
        columnspacing=1.2,
        **kw,
    )


def _scene_title(task, env) -> str:
    parts = [task.name]
    if env.extra_objects:
        parts.append("+ extra objects")
    if env.rotation_deg:
        parts.append(f"rotated {env.rotation_deg:g}°")
    return " ".join(parts)


def _fig_size(task, panels: int = 1) -> tuple[float, float]:
    return (4.6 * panels, 4.4) if task.dim == 3 else (3.6 * panels, 3.8)


# --------------------------------------------------------------------------------------------- figures
def task_figure(task, env, q=None, out: str | Path | None = None) -> Figure:
    """The task's environment with the robot at configuration q (``mpd tasks show``)."""
    with style():
        fig = Figure(figsize=_fig_size(task), layout="constrained")
        ax = new_task_axes(fig, task)
        draw_environment(ax, env)
        if q is not None:
            draw_robot(ax, task, q)
        ax.set_title(_scene_title(task, env), fontsize=8.5)
    return _finish(fig, out)


def draw_paths_figure(
    task,
    env,
    paths,
    valid=None,
    out: str | Path | None = None,
    title: str | None = None,
    max_paths: int = 100,
    goal_pos=None,
) -> Figure:
    """A batch of dense joint paths (N, n, dof) in task space (end-effector paths for arms) over the scene."""
    with style():
        fig = Figure(figsize=_fig_size(task), layout="constrained")
        ax = new_task_axes(fig, task)
        draw_environment(ax, env)
        counts = draw_paths(ax, task, paths, valid, max_paths=max_paths, goal_pos=goal_pos)
        if title is None:
            title = _scene_title(task, env)
            if counts["valid"] >= 0:
                title += f"\n{counts['valid']}/{counts['total']} valid"
        ax.set_title(title, fontsize=8.5)
        _legend(fig, counts)
    return _finish(fig, out)


def _unit(task, j: int) -> str:
    return "rad" if task.robot.chain.revolute[j] else "m"


RASTER_ABOVE = 100  # samples per figure above which the joint-space lines are drawn as an image in vector formats


def trajectory_figure(task, env, q, dq, ddq, valid, out: str | Path | None = None, title: str | None = None) -> Figure:
    """One context: task space (left) and joint position / velocity / acceleration against time (right), one
    line per sample and joint, dashed joint limits. q, dq, ddq: (B, n, dof) in time units."""
    q, dq, ddq = _np(q), _np(dq), _np(ddq)
    B, n, dof = q.shape
    v = _mask(valid, B)
    robot = task.robot
    t = np.linspace(0.0, task.spec.trajectory.duration, n)
    limits = [
        (robot.q_min.numpy(), robot.q_max.numpy()),
        (-robot.dq_max.numpy(), robot.dq_max.numpy()) if robot.dq_max is not None else None,
        (-robot.ddq_max.numpy(), robot.ddq_max.numpy()) if robot.ddq_max is not None else None,
    ]
    rows = [(q, "position"), (dq, "velocity"), (ddq, "acceleration")]
    unit_pow = ["", "/s", "/s²"]
    left_w = 4.6 if task.dim == 3 else 4.0
    with style():
        fig = Figure(figsize=(left_w + 1.75 * dof, 5.0), layout="constrained")
        gs = fig.add_gridspec(3, dof + 1, width_ratios=[left_w / 1.6] + [1.0] * dof)
        ax0 = new_task_axes(fig, task, gs[:, 0])
        draw_environment(ax0, env)
        counts = draw_paths(ax0, task, q, v)
        ax0.set_title(_scene_title(task, env) if title is None else title, fontsize=8.5)
        order = np.argsort(v, kind="stable") if v is not None else np.arange(B)  # valid drawn last, on top
        colors = [(VALID if v[i] else INVALID) if v is not None else UNKNOWN for i in order]
        first = None
        for r, (data, label) in enumerate(rows):
            for j in range(dof):
                ax = fig.add_subplot(gs[r, j + 1], sharex=first)
                first = first or ax
                segs = np.stack([np.broadcast_to(t, (B, n)), data[:, :, j]], -1)[order]
                # many samples (a batch of 1000: 21,000 lines) rasterized, or a PDF grows past 10 MB
                lines = LineCollection(
                    list(segs), colors=colors, linewidths=0.8, alpha=0.75, rasterized=B > RASTER_ABOVE
                )
                ax.add_collection(lines)
                lo, hi = float(data[:, :, j].min()), float(data[:, :, j].max())
                if limits[r] is not None:
                    for lim in (limits[r][0][j], limits[r][1][j]):
                        ax.axhline(lim, color=LIMIT, linestyle="--", linewidth=0.9, zorder=0)
                    lo, hi = min(lo, limits[r][0][j]), max(hi, limits[r][1][j])
                pad = 0.06 * (hi - lo) if hi > lo else 0.1
                ax.set_ylim(lo - pad, hi + pad)
                ax.set_xlim(t[0], t[-1])
                ax.yaxis.set_major_locator(MaxNLocator(4))
                ax.xaxis.set_major_locator(MaxNLocator(3))
                ax.grid(True, linewidth=0.3, color="0.88")
                if r == 0:
                    ax.set_title(robot.joint_names[j].removeprefix("panda_"), fontsize=8)
                if r == 2:
                    ax.set_xlabel("t [s]", labelpad=1)
                else:
                    ax.tick_params(labelbottom=False)
                if j == 0:
                    ax.set_ylabel(f"{label} [{_unit(task, j)}{unit_pow[r]}]", fontsize=8)
        _legend(fig, counts, ncol=5)
    return _finish(fig, out)


def denoising_figure(
    task, env, steps: Sequence[tuple[str, np.ndarray, np.ndarray]], out: str | Path | None = None
) -> Figure:
    """Samples at several denoising steps (the paper's Fig. 11, bottom row): one panel per (label, dense paths
    (B, n, dof), valid mask), valid in orange."""
    if not steps:
        raise ValueError("denoising_figure needs at least one (label, paths, valid) step")
    k = len(steps)
    # equal-aspect 2-D panels are as tall as they are wide: the height adds room for titles, labels and the
    # legend, which the constrained layout cannot find once the aspect pins the axes
    w, h = (3.4, 3.9) if task.dim == 3 else (2.7, 3.8)
    with style():
        fig = Figure(figsize=(w * k, h), layout="constrained")
        gs = fig.add_gridspec(1, k)
        counts = None
        for i, (label, paths, valid) in enumerate(steps):
            ax = new_task_axes(fig, task, gs[0, i])
            draw_environment(ax, env)
            counts = draw_paths(ax, task, paths, valid, robot_goal=False, robot_alpha=0.45)
            sub = f"{counts['valid']}/{counts['total']} valid" if counts["valid"] >= 0 else f"{counts['total']} samples"
            ax.set_title(f"{label}\n{sub}", fontsize=8.5)
            if i > 0 and task.dim == 2:
                ax.set_ylabel("")
                ax.tick_params(labelleft=False)
        _legend(fig, counts)
    return _finish(fig, out)


__all__ = [
    "draw_environment",
    "draw_paths",
    "draw_paths_figure",
    "draw_robot",
    "denoising_figure",
    "new_task_axes",
    "save_figure",
    "style",
    "task_figure",
    "trajectory_figure",
]
