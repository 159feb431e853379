"""Rerun recordings (rerun-sdk 0.41) of one (cell, context): the scene, the robot, the samples at every denoising or
optimization step, and the final trajectories.

One ``.rrd`` per recorded (cell, context), written without spawning a viewer (``mpd view`` opens them):

- ``world/environment/{obstacles,extra}``: obstacles grey, extra objects red. 2-D tasks lie in the z = 0 plane:
  discs as flat cylinders and boxes as flat boxes just below it, so the paths drawn at z = 0 stay on top.
- ``world/robot``: the Panda through Rerun's URDF importer (meshes, ``/tf_static``), its joints driven by
  ``rr.urdf`` joint transforms on ``world/robot/joints/<joint>``; planar arms as a line strip through the joint
  frames plus their collision spheres; the point mass as a ball. At the start configuration on the
  ``denoising_step`` timeline, animated along the best trajectory (the first valid one with the shortest
  joint-space path) on the ``time`` timeline (seconds, from the task's duration).
- ``world/samples``: the batch at every step on ``denoising_step`` (valid orange, invalid black): the paths of 2-D
  tasks, end-effector paths of arms.
- ``world/final``: the final trajectories on ``time``: the whole paths, the current position of every sample, the
  best path.
- ``plots/*``: the best trajectory's joint positions against time, the fraction of valid samples per step;
  ``info``: the cell's parameters.

A default blueprint (3-D scene on the left, plots and the cell on the right) makes the viewer open on that layout.
"""

from __future__ import annotations

import json
import os
import warnings
import zipfile
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mpd.experiments.tracking import AXIS_PREFIXES, CELL_COLUMNS
from mpd.viz.scene import EXTRA, GOAL, INVALID, OBSTACLE, ROBOT, START, VALID

TIME = "time"
STEP = "denoising_step"
MAX_PATHS = 256  # samples drawn per step; more only makes the file large and the view unreadable
APP = "mpd"

# the run's cell axes that can tell two recordings of one (task, method, scene) apart, in naming order
_DISTINGUISH = ("parametrization", "sampler", "preset", "n_samples", "seed", "overrides")


# ----------------------------------------------------------------------------------------------- helpers
def _rgba(color: str, alpha: float = 1.0) -> list[int]:
    from matplotlib.colors import to_rgba

    return [round(255 * c) for c in to_rgba(color, alpha)]


def _as_task(task):
    if isinstance(task, str | Path):
        from mpd.tasks import load_task

        return load_task(task)
    return task


def _is_point_mass(task) -> bool:
    return task.robot.n_spheres == 1 and task.robot.dof == task.dim


def task_points(task, q: np.ndarray) -> np.ndarray:
    """(..., dof) configurations -> (..., 3) points drawn for them: the point mass itself (z = 0) or the end
    effector."""
    q = np.asarray(q, dtype=np.float64)
    if _is_point_mass(task):
        return np.concatenate([q, np.zeros((*q.shape[:-1], 3 - q.shape[-1]))], axis=-1)
    # float32: for drawing, and twice as fast as float64 on the S x B x 128 configurations of a recording
    flat = torch.as_tensor(q.reshape(-1, task.dof), dtype=torch.float32)
    out = []
    for chunk in torch.split(flat, 65536):  # bounded memory
        p, _ = task.robot.ee_pose(chunk)
        out.append(p.double().numpy())
    return np.concatenate(out).reshape(*q.shape[:-1], 3)


def path_lengths(q: np.ndarray) -> np.ndarray:
    """Joint-space length of dense paths (B, n, dof) -> (B,) (as ``mpd.metrics.path_length``)."""
    return np.linalg.norm(np.diff(np.asarray(q, dtype=np.float64), axis=1), axis=-1).sum(-1)


def best_index(q: np.ndarray, valid: np.ndarray | None) -> tuple[int, bool]:
    """(index, is_valid): the first valid trajectory with the shortest path; without a valid one, the shortest."""
    lengths = path_lengths(q)
    v = np.ones(len(q), bool) if valid is None else np.asarray(valid, bool).reshape(-1)
    if v.any():
        idx = np.flatnonzero(v)
        return int(idx[np.argmin(lengths[idx])]), True  # argmin keeps the first of equal lengths
    return int(np.argmin(lengths)), False


def _subset(n: int, k: int = MAX_PATHS) -> np.ndarray:
    """Evenly spaced indices (deterministic; keeps the valid/invalid mix)."""
    if n <= k:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, k).round().astype(int))


def _quat_xyzw(rotation: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    r = np.eye(3)
    r[: rotation.shape[0], : rotation.shape[1]] = rotation
    return Rotation.from_matrix(r).as_quat().tolist()  # scipy's order is (x, y, z, w), as Rerun's


def _scale(task) -> float:
    lo, hi = task.env().workspace
    return float(np.max(np.asarray(hi) - np.asarray(lo)))


# ------------------------------------------------------------------------------------------------ scene
def _log_environment(rec, task, env) -> None:
    import rerun as rr

    flat = task.dim == 2
    thick = 0.02 * _scale(task)  # height of the 2-D obstacles, extruded below the z = 0 plane
    for extra, name in ((False, "obstacles"), (True, "extra")):
        prims = [p for p, e in env.primitives if e == extra]
        color = _rgba(EXTRA if extra else OBSTACLE)
        sph = [p for p in prims if p.kind == "sphere"]
        box = [p for p in prims if p.kind == "box"]
        path = f"world/environment/{name}"
        if sph and flat:
            rec.log(
                f"{path}/discs",
                rr.Cylinders3D(
                    centers=[[*p.centre[:2], -thick / 2 - 1e-3 * thick] for p in sph],
                    radii=[p.radius for p in sph],
                    lengths=[thick] * len(sph),
                    colors=color,
                    fill_mode="solid",
                ),
                static=True,
            )
        elif sph:
            rec.log(
                f"{path}/spheres",
                rr.Ellipsoids3D(
                    centers=[p.centre for p in sph],
                    half_sizes=[[p.radius] * 3 for p in sph],
                    colors=color,
                    fill_mode="solid",
                ),
                static=True,
            )
        if box:
            rec.log(
                f"{path}/boxes",
                rr.Boxes3D(
                    centers=[[*p.centre[:2], -thick / 2 - 1e-3 * thick] if flat else p.centre for p in box],
                    half_sizes=[[*p.half_size[:2], thick / 2] if flat else p.half_size for p in box],
                    quaternions=[_quat_xyzw(p.rotation) for p in box],
                    colors=color,
                    fill_mode="solid",
                ),
                static=True,
            )
    if flat:  # the workspace's frame: the 2-D figures' border
        lo, hi = env.workspace
        loop = [[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0], [lo[0], lo[1], 0]]
        rec.log("world/environment/workspace", rr.LineStrips3D([loop], colors=[60, 60, 60]), static=True)


# ------------------------------------------------------------------------------------------------ robot
def _log_panda(rec, task, q_start: np.ndarray, q_best: np.ndarray, times: np.ndarray) -> None:
    """The URDF through Rerun's importer; joint transforms from rr.urdf at the start (``denoising_step``) and
    along the best trajectory (``time``)."""
    import rerun as rr
    import rerun.urdf as rru

    urdf = task.robot.spec.urdf.resolve()
    # the importer resolves package:// mesh URIs through ROS_PACKAGE_PATH (pybullet_data's Panda uses them)
    roots = os.environ.get("ROS_PACKAGE_PATH", "")
    if str(urdf.parent) not in roots.split(os.pathsep):
        os.environ["ROS_PACKAGE_PATH"] = os.pathsep.join([str(urdf.parent)] + ([roots] if roots else []))
    rec.log_file_from_path(urdf, entity_path_prefix="world/robot", static=True)
    tree = rru.UrdfTree.from_file_path(urdf, entity_path_prefix="world/robot")
    # the URDF's root link is a named frame of its own: hang it on the robot's entity so that it sits in the
    # world of the obstacles (the robot's base is the world origin in every task)
    rec.log(
        "world/robot/base",
        rr.Transform3D(parent_frame="tf#/world/robot", child_frame=tree.root_link().name),
        static=True,
    )
    fixed = dict(task.robot.spec.urdf.fixed_joints)  # the fingers, held open as in the planner's model
    names = list(task.robot.joint_names)
    step0 = [rr.TimeColumn(STEP, sequence=[0])]
    for j in tree.joints():
        path = f"world/robot/joints/{j.name}"
        if j.name in names:
            k = names.index(j.name)
            # clamp=False: the official limits are what the planner uses; the URDF's are only slightly wider
            rec.send_columns(path, indexes=step0, columns=j.compute_transform_columns([float(q_start[k])], clamp=False))
            rec.send_columns(
                path,
                indexes=[rr.TimeColumn(TIME, duration=times)],
                columns=j.compute_transform_columns(q_best[:, k].astype(float).tolist(), clamp=False),
            )
        elif j.name in fixed:
            rec.log(path, j.compute_transform(float(fixed[j.name]), clamp=False), static=True)


def _log_simple_robot(rec, task, q_start: np.ndarray, q_best: np.ndarray, times: np.ndarray) -> None:
    """Planar arms: links as a line strip through the joint frames and the collision spheres; the point mass: a
    ball. Both at the start on ``denoising_step`` and along the best trajectory on ``time``."""
    import rerun as rr

    robot = task.robot
    radii = robot.sphere_radii.numpy()
    q = np.concatenate([q_start[None], q_best]).astype(np.float64)
    if _is_point_mass(task):
        centres = task_points(task, q)[:, None]
        frames = None
    else:
        kin = robot.kinematics(torch.as_tensor(q))
        centres = kin.points.numpy()
        frames = np.concatenate([np.zeros((len(q), 1, 3)), kin.origins.numpy(), kin.ee_pos.numpy()[:, None]], axis=1)
    body = _rgba(ROBOT)
    light = _rgba(ROBOT, 0.45)
    for i in range(len(q)):
        if i == 0:
            rec.set_time(STEP, sequence=0)
            rec.disable_timeline(TIME)
        else:
            rec.set_time(TIME, duration=times[i - 1])
            rec.disable_timeline(STEP)
        if frames is None:
            rec.log("world/robot/body", rr.Points3D(centres[i], radii=radii, colors=body))
            continue
        rec.log("world/robot/links", rr.LineStrips3D([frames[i]], radii=0.25 * radii.max() + 0.004, colors=body))
        rec.log("world/robot/joints", rr.Points3D(frames[i, :-1], radii=0.4 * radii.max() + 0.006, colors=[30] * 3))
        rec.log("world/robot/spheres", rr.Points3D(centres[i], radii=radii, colors=light))
    rec.reset_time()


# -------------------------------------------------------------------------------------------- recording
def _colors(valid: np.ndarray | None, n: int) -> np.ndarray:
    if valid is None:
        return np.tile(_rgba(VALID), (n, 1))
    return np.where(np.asarray(valid, bool)[:, None], _rgba(VALID), _rgba(INVALID, 0.6)).astype(np.uint8)


def _blueprint(task, steps: bool):
    import rerun.blueprint as rrb

    overrides = {}
    if task.robot.spec.urdf is not None:  # the importer logs collision meshes too; the visual ones suffice
        overrides["world/robot/panda/collision_geometries"] = rrb.EntityBehavior(visible=False)
    eye = None
    if task.dim == 2:  # a top view of the plane
        lo, hi = task.env().workspace
        c = (np.asarray(lo) + np.asarray(hi)) / 2
        eye = rrb.EyeControls3D(
            # nearly straight down, z up: orbiting then spins the plane about z, as one expects
            position=[float(c[0]), float(c[1]) - 0.25 * _scale(task), 1.6 * _scale(task)],
            look_target=[float(c[0]), float(c[1]), 0.0],
            eye_up=[0.0, 0.0, 1.0],
        )
    scene = rrb.Spatial3DView(
        origin="/world", name=task.name, overrides=overrides, eye_controls=eye, background=[255, 255, 255]
    )
    side = [rrb.TimeSeriesView(origin="/plots/joints", name="best trajectory: joint positions")]
    if steps:
        side.append(rrb.TimeSeriesView(origin="/plots/valid", name="valid samples per step"))
    side.append(rrb.TextDocumentView(origin="/info", name="cell"))
    return rrb.Blueprint(
        rrb.Horizontal(scene, rrb.Vertical(*side), column_shares=[3, 1]),
        rrb.TimePanel(timeline=STEP if steps else TIME, state="expanded"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        auto_views=False,
    )


# the cell's parameters (the task is the recording's own title), then where the row sits in the run
_INFO_AXES = tuple(c for c in CELL_COLUMNS if c != "task") + ("context_index", "cell_key")
_INFO_METRICS = ("success", "fraction_valid", "vendi", "ee_pos_error", "ee_ori_error_deg", "best_path_length")


def _info_markdown(task, params: Mapping[str, Any], n: int, n_valid: int, best: int, best_valid: bool) -> str:
    """The cell in a few lines: its axes (and planner.* settings), the context, the metrics when given."""
    why = "valid, shortest path" if best_valid else "no valid one: the shortest"
    keys = [k for k in _INFO_AXES if k in params] + sorted(k for k in params if str(k).startswith(AXIS_PREFIXES))
    lines = [f"## {task.name}", "", "| parameter | value |", "| --- | --- |"]
    lines += [f"| {k} | {params[k]} |" for k in keys if params[k] not in (None, "")]
    mets = [k for k in _INFO_METRICS if isinstance(params.get(k), int | float)]
    if mets:
        lines += ["", "| metric | value |", "| --- | --- |"] + [f"| {k} | {float(params[k]):.4g} |" for k in mets]
    lines += [
        "",
        f"{n_valid} of {n} final trajectories valid (orange; invalid black)." if n_valid >= 0 else f"{n} samples.",
        f"Robot animated along trajectory {best} ({why}).",
        "",
        "Timelines: `denoising_step` (the batch at every step), `time` (the final trajectories, seconds).",
    ]
    return "\n".join(lines)


def _log_steps(rec, task, history: Mapping[str, np.ndarray]) -> None:
    """The batch at every denoising / optimization step on ``denoising_step``, and its fraction valid."""
    import rerun as rr

    sq = np.asarray(history["steps_q"])
    S = sq.shape[0]
    idx = _subset(sq.shape[1])
    sv = history.get("steps_valid")
    labels = history.get("steps_label")
    x = task_points(task, sq[:, idx])  # (S, k, n, 3)
    frac = []
    for s in range(S):
        v = None if sv is None else np.asarray(sv[s], bool)
        rec.set_time(STEP, sequence=s)
        colors = _colors(None if v is None else v[idx], len(idx))
        rec.log("world/samples", rr.LineStrips3D(list(x[s]), radii=0.0015 * _scale(task), colors=colors))
        if labels is not None:
            rec.log("info/step", rr.TextLog(str(labels[s])))
        frac.append(np.nan if v is None else float(v.mean()))
    rec.reset_time()
    rec.log("plots/valid", rr.SeriesLines(names="fraction valid", colors=_rgba(VALID)), static=True)
    rec.send_columns(
        "plots/valid",
        indexes=[rr.TimeColumn(STEP, sequence=np.arange(S))],
        columns=rr.Scalars.columns(scalars=np.asarray(frac)),
    )


def _log_final(rec, task, q: np.ndarray, valid: np.ndarray | None, best: int, times: np.ndarray) -> None:
    """The final trajectories on ``time``: whole paths (at t = 0, so shown all along), every sample's current
    point, the best path; and the best trajectory's joint positions against time."""
    import rerun as rr

    n = q.shape[1]
    idx = _subset(len(q))
    x = task_points(task, q[idx])  # (k, n, 3)
    colors = _colors(None if valid is None else valid[idx], len(idx))
    rec.set_time(TIME, duration=times[0])
    rec.log("world/final/paths", rr.LineStrips3D(list(x), radii=0.0012 * _scale(task), colors=colors))
    xb = task_points(task, q[best])
    rec.log("world/final/best", rr.LineStrips3D([xb], radii=0.003 * _scale(task), colors=_rgba(ROBOT)))
    rec.reset_time()
    rec.send_columns(
        "world/final/samples",
        indexes=[rr.TimeColumn(TIME, duration=times)],
        columns=rr.Points3D.columns(
            positions=x.transpose(1, 0, 2).reshape(-1, 3),
            colors=np.tile(colors, (n, 1)),
            radii=np.full(n * len(idx), 0.004 * _scale(task), np.float32),
        ).partition([len(idx)] * n),
    )
    for k, name in enumerate(task.robot.joint_names):
        ent = f"plots/joints/{name}"
        rec.log(ent, rr.SeriesLines(names=name), static=True)
        rec.send_columns(
            ent, indexes=[rr.TimeColumn(TIME, duration=times)], columns=rr.Scalars.columns(scalars=q[best, :, k])
        )


def record_history(
    path: str | Path,
    task,
    params: Mapping[str, Any],
    history: Mapping[str, np.ndarray],
    blueprint: bool = True,
    env=None,
) -> Path:
    """Write the Rerun recording of one (cell, context) to ``path`` (``.rrd``); returns the path.

    ``task``: a :class:`mpd.tasks.Task` or its name. ``params``: the cell's parameters (``extra_objects``,
    ``rotation_deg``, ``method``, ...; a results row will do). ``history``: ``q`` (B, n, dof) final dense
    trajectories in time, ``valid`` (B,), optionally ``steps_q`` (S, B, n, dof), ``steps_valid`` (S, B) and
    ``steps_label`` (S,) (the runner's recorded history). ``env``: the scene to draw (default: the task's, as
    ``params`` says; e.g. one with obstacles given at plan time).
    """
    import rerun as rr

    task = _as_task(task)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if env is None:
        env = task.env(bool(params.get("extra_objects") or False), float(params.get("rotation_deg") or 0.0))
    q = np.asarray(history["q"], dtype=np.float64)
    valid = np.asarray(history["valid"], bool).reshape(-1) if history.get("valid") is not None else None
    best, best_valid = best_index(q, valid)
    # integer nanoseconds: set_time(float seconds) and TimeColumn(float array) round differently, which would
    # split one instant into two entries of the timeline
    seconds = np.linspace(0.0, float(task.spec.trajectory.duration), q.shape[1])
    times = np.round(seconds * 1e9).astype(np.int64).astype("timedelta64[ns]")
    has_steps = history.get("steps_q") is not None and len(history["steps_q"]) > 0

    rid = f"{params.get('cell_key', '')}-ctx{params.get('context_index', 0)}-{path.stem}"
    rec = rr.RecordingStream(f"{APP}-{task.name}", recording_id=rid)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.rrd")
    rec.save(tmp, default_blueprint=_blueprint(task, has_steps) if blueprint else None)
    try:
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        _log_environment(rec, task, env)
        log_robot = _log_panda if task.robot.spec.urdf is not None else _log_simple_robot
        log_robot(rec, task, q[best, 0], q[best], times)
        # start and goal markers (the goal: where the best trajectory ends)
        pts = task_points(task, np.stack([q[best, 0], q[best, -1]]))
        size = 0.012 * _scale(task)
        rec.log("world/start", rr.Points3D(pts[:1], radii=size, colors=_rgba(START)), static=True)
        rec.log("world/goal", rr.Points3D(pts[1:], radii=size, colors=_rgba(GOAL)), static=True)
        if has_steps:
            _log_steps(rec, task, history)
        _log_final(rec, task, q, valid, best, times)
        n_valid = int(valid.sum()) if valid is not None else -1
        info = _info_markdown(task, params, len(q), n_valid, best, best_valid)
        rec.log("info", rr.TextDocument(info, media_type="text/markdown"), static=True)
    except BaseException:
        rec.disconnect()
        tmp.unlink(missing_ok=True)  # no half recording under any name
        raise
    rec.disconnect()  # writes the footer; without it the file reads as truncated
    os.replace(tmp, path)
    return path


# ------------------------------------------------------------------------------------------------- runs
def _component(value: Any) -> str:
    """A value as one file-name component (no separators: a recording never lands outside ``recordings/``)."""
    return "".join(ch if ch.isalnum() or ch in "._-" else "_" for ch in str(value)).lstrip(".") or "_"


def recording_name(params: Mapping[str, Any], context_index: int, cells: Sequence[Mapping[str, Any]] = ()) -> str:
    """``<task>-<method>-<train|extra>[-rot<deg>][-<axis values>]-ctx<i>.rrd``. ``cells`` (the run's manifest
    cells) decide which further axes must be named: those that differ between cells of the same task, method
    and scene (e.g. ``-n10`` in a batch-size study)."""

    def base(p) -> tuple:
        return (p.get("task"), p.get("method"), bool(p.get("extra_objects")), float(p.get("rotation_deg") or 0))

    parts = [_component(params.get("task")), _component(params.get("method"))]
    parts.append("extra" if params.get("extra_objects") else "train")
    rot = float(params.get("rotation_deg") or 0.0)
    if rot:
        parts.append(f"rot{rot:g}")
    same = [c for c in cells if base(c) == base(params)]
    for axis in _DISTINGUISH:
        if len({str(c.get(axis)) for c in same}) > 1:
            value = params.get(axis)
            if axis == "n_samples":
                parts.append(f"n{value}")
            elif axis == "seed":
                parts.append(f"seed{value}")
            elif value not in (None, ""):
                parts.append("".join(ch if ch.isalnum() or ch in "._" else "_" for ch in str(value)))
    return "-".join(parts) + f"-ctx{int(context_index)}.rrd"


def recording_path(
    run_dir: str | Path, params: Mapping[str, Any], cells: Sequence[Mapping[str, Any]] | None = None
) -> Path:
    """Where the recording of a (cell, context) goes: ``run_dir/recordings/<recording_name>`` (``params`` holds
    ``context_index``, as a results row does). ``cells`` default to the run manifest's, as ``record_run`` uses,
    so that a recording streamed by the runner and one rebuilt later get the same name."""
    run_dir = Path(run_dir)
    if cells is None:
        man = run_dir / "manifest.json"
        cells = json.loads(man.read_text()).get("cells", []) if man.exists() else []
    return run_dir / "recordings" / recording_name(params, int(params.get("context_index", 0)), cells)


def load_history(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A recorded (cell, context) from ``histories/<cell_key>-ctx<i>.npz``: (arrays, row parameters; the latter
    empty for histories written before the row was stored with them)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k not in ("row_json", "row_key")}
            params = json.loads(str(z["row_json"])) if "row_json" in z.files else {}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:  # truncated or overwritten
        raise ValueError(f"{path}: the recorded history does not read back ({type(e).__name__}: {e})") from None
    stem = path.stem
    if "-ctx" in stem:
        key, ctx = stem.rsplit("-ctx", 1)
        params.setdefault("cell_key", key)
        params.setdefault("context_index", int(ctx))
    return arrays, params


def run_task(run_dir: str | Path, name: str):
    """A task of a run by its name: the file recorded in the manifest (a task the spec gave by path), else the
    bundled task of that name."""
    from mpd.paths import REPO_ROOT
    from mpd.tasks import load_task

    man = Path(run_dir) / "manifest.json"
    files = json.loads(man.read_text()).get("task_files", {}) if man.exists() else {}
    entry = files.get(name)
    if entry is None:
        return load_task(name)
    path = Path(entry["path"])
    return load_task(path if path.is_absolute() else Path(REPO_ROOT) / path)


def _params_from_run(run_dir: Path, cell_key: str) -> dict[str, Any]:
    """Parameters of a cell from the manifest (older histories do not carry them)."""
    man = json.loads((run_dir / "manifest.json").read_text())
    for c in man.get("cells", []):
        if c.get("key") == cell_key:
            return {k: v for k, v in c.items() if k != "key"}
    return {}


def record_run(run_dir: str | Path, force: bool = False, histories: Iterable[Path] | None = None) -> list[Path]:
    """(Re)build ``run_dir/recordings/*.rrd`` from ``run_dir/histories/*.npz``; a recording newer than its
    history is kept unless ``force``. Returns the recordings' paths, sorted."""
    run_dir = Path(run_dir)
    files = sorted(histories if histories is not None else (run_dir / "histories").glob("*.npz"))
    if not files:
        return []
    man_path = run_dir / "manifest.json"
    cells = json.loads(man_path.read_text()).get("cells", []) if man_path.exists() else []
    out = []
    for f in files:
        try:
            arrays, params = load_history(f)
        except ValueError as e:  # one damaged history costs its recording only
            warnings.warn(f"{e}; its recording is not rebuilt", stacklevel=2)
            continue
        if "task" not in params:
            params = {**_params_from_run(run_dir, params["cell_key"]), **params}
        if "task" not in params:
            raise ValueError(f"{f}: no parameters for cell {params.get('cell_key')} in the history nor the manifest")
        target = recording_path(run_dir, params, cells)
        if force or not target.exists() or target.stat().st_mtime < f.stat().st_mtime:
            record_history(target, run_task(run_dir, params["task"]), params, arrays)
        out.append(target)
    return sorted(out)


__all__ = [
    "STEP",
    "TIME",
    "best_index",
    "load_history",
    "record_history",
    "record_run",
    "recording_name",
    "recording_path",
    "run_task",
]


def stream_unit(run_dir: Path, task_file: str, row: Mapping, history: Mapping[str, np.ndarray]) -> None:
    """The recorder a runner streams recorded (cell, context) units through (``Runner(recorder=stream_unit)``): the
    unit's Rerun recording in ``run_dir/recordings/``."""
    record_history(recording_path(run_dir, row), task_file, row, history)
