"""The pinned evaluation protocol: which contexts a run plans for, per (task, scene), as content-addressed files.

By default (``source = "held-out"``) the contexts come from the dataset's held-out paths, as the authors' evaluation
takes them from their held-out split: the forward paths of the ``test`` split, then of the ``val`` split (both are
kept out of training), in the order of a permutation seeded by the *context seed* (a spec's ``context_seed``,
separate from the seeds of the sampling noise). A candidate is kept when its start and goal are at least the task's
``[context].min_start_goal_distance`` apart (the authors' evaluation minimum) and both are valid, with the task's
clearance, in the training scene; the first ``n`` kept candidates are the task's contexts. In another scene (extra
objects, a rotation) a context whose start or goal is invalid there is skipped, in that scene only, as the authors
skip it; the file says which and how many.

``source = "sampled"`` keeps mpd's earlier protocol, independent of any dataset: contexts drawn uniformly with the
clearance in the extra-objects scene and solvable by RRTConnect in the training scene
(:func:`mpd.data.contexts.evaluation_contexts`); the same contexts in every scene.

A set is identified by the sha256 of its arrays and stored as ``<cache>/contexts/<task>-<scene>-<hash16>.npz`` with a
JSON sidecar of what made it (dataset content hash, seed, source, candidate counts, skipped contexts); every results
row carries the hash (``contexts_hash``). ``mpd data contexts`` lists and exports them.
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpd.paths import cache_dir
from mpd.tasks import Task

SOURCES = ("held-out", "sampled")
# the held-out splits, in the order they are used (names of mpd.data.dataset.SPLITS)
HELD_OUT = ("test", "val")
CONTEXT_ARRAYS = ("q_start", "q_goal", "ee_pos", "ee_rot", "context_id")


@dataclass
class ContextSet:
    """The evaluation contexts of one (task, scene): rows ``i`` of the arrays; ``index`` is each context's position in
    the task's list (the same context has the same index in every scene, so scenes and methods pair up by it)."""

    task: str
    scene: str
    q_start: np.ndarray  # (n, dof)
    q_goal: np.ndarray  # (n, dof) the dataset's goal configuration (a reference only, for EE-goal tasks)
    index: np.ndarray  # (n,) position in the task's context list
    context_id: np.ndarray  # (n,) dataset context id (-1 for sampled contexts)
    ee_pos: np.ndarray | None = None
    ee_rot: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.q_start)

    @property
    def hash(self) -> str:
        return self.meta["sha256"]

    def row(self, i: int) -> dict[str, np.ndarray]:
        out = {"q_start": self.q_start[i], "q_goal": self.q_goal[i]}
        if self.ee_pos is not None:
            out["ee_pos"], out["ee_rot"] = self.ee_pos[i], self.ee_rot[i]
        return out

    @classmethod
    def from_arrays(cls, task: str, scene: str, arrays: dict[str, np.ndarray], meta: dict) -> ContextSet:
        """A set from the arrays of :meth:`arrays` (``index`` and ``context_id`` included)."""
        return cls(
            task,
            scene,
            arrays["q_start"],
            arrays["q_goal"],
            arrays["index"],
            arrays["context_id"],
            arrays.get("ee_pos"),
            arrays.get("ee_rot"),
            meta,
        )

    def arrays(self) -> dict[str, np.ndarray]:
        out = {"q_start": self.q_start, "q_goal": self.q_goal, "index": self.index, "context_id": self.context_id}
        if self.ee_pos is not None:
            out["ee_pos"], out["ee_rot"] = self.ee_pos, self.ee_rot
        return out


def scene_name(extra_objects: bool, rotation_deg: float = 0.0) -> str:
    name = "extra-objects" if extra_objects else "training"
    return name if not rotation_deg else f"{name}-rot{float(rotation_deg):g}"


def arrays_sha256(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over the arrays in a fixed order, each as (name, dtype, shape, C-order bytes)."""
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def held_out_candidates(task: Task, dataset, seed: int) -> dict[str, np.ndarray]:
    """The held-out forward contexts of a dataset, test split first then val, each split permuted by ``seed``."""
    from mpd.data.dataset import SPLITS

    parts = []
    for k, split in enumerate(HELD_OUT):
        sel = np.flatnonzero((dataset.split == SPLITS.index(split)) & ~dataset.reversed)
        rng = np.random.default_rng([int(seed), k])
        parts.append(sel[rng.permutation(len(sel))])
    order = np.concatenate(parts)
    out = {
        "q_start": dataset.q_start[order],
        "q_goal": dataset.q_goal[order],
        "context_id": dataset.context_id[order].astype(np.int64),
    }
    if task.ee_goal:
        out["ee_pos"], out["ee_rot"] = dataset.ee_pos[order], dataset.ee_rot[order]
    return out


def _valid(task: Task, q: np.ndarray, extra_objects: bool, rotation_deg: float) -> np.ndarray:
    from mpd.data.checkers import SphereChecker

    if len(q) == 0:
        return np.zeros(0, dtype=bool)

    chk = SphereChecker(
        task, extra_objects=extra_objects, clearance=task.spec.collision.clearance, rotation_deg=rotation_deg
    )
    try:
        return chk.valid(np.asarray(q, dtype=np.float64))
    finally:
        chk.close()


def _ends_valid(task: Task, q_start: np.ndarray, q_goal: np.ndarray, extra_objects: bool, rotation_deg: float):
    """Start and goal both valid in the scene: one checker, one batched check of both ends."""
    v = _valid(task, np.concatenate([q_start, q_goal]), extra_objects, rotation_deg)
    return v[: len(q_start)] & v[len(q_start) :]


def task_contexts(task: Task, dataset, n: int, seed: int = 0) -> ContextSet:
    """The task's list of n held-out contexts (valid in the training scene, far enough apart)."""
    cand = held_out_candidates(task, dataset, seed)
    far = np.linalg.norm(cand["q_goal"] - cand["q_start"], axis=1) >= task.spec.context.min_start_goal_distance
    ok = far & _ends_valid(task, cand["q_start"], cand["q_goal"], False, 0.0)
    keep = np.flatnonzero(ok)
    if len(keep) < n:
        raise ValueError(
            f"{task.name}: dataset {dataset.name} has {len(keep)} usable held-out contexts ({len(ok)} held-out, "
            f"{int((~far).sum())} closer than min_start_goal_distance = {task.spec.context.min_start_goal_distance}), "
            f"fewer than the {n} asked for: use a larger dataset or fewer contexts"
        )
    keep = keep[:n]
    meta = {
        "source": "held-out",
        "task": task.name,
        "dataset": dataset.name,
        "dataset_hash": dataset.info.get("content_hash"),
        "context_seed": int(seed),
        "n_held_out": int(len(ok)),
        "n_too_close": int((~far).sum()),
        "n_invalid_training_scene": int((far & ~ok).sum()),
        "min_start_goal_distance": task.spec.context.min_start_goal_distance,
        "clearance": task.spec.collision.clearance,
    }
    arrays = {k: v[keep] for k, v in cand.items()}
    return ContextSet(
        task.name,
        "task",
        arrays["q_start"],
        arrays["q_goal"],
        np.arange(n, dtype=np.int64),
        arrays["context_id"],
        arrays.get("ee_pos"),
        arrays.get("ee_rot"),
        meta,
    )


def turn_configurations(task: Task, q: np.ndarray, rotation_deg: float) -> np.ndarray:
    """The configurations that place the robot as ``q`` does, turned about the base's z axis by ``rotation_deg``
    (every collision sphere at R_z q's): the first joint turned when it is a rotation about the base z axis (the
    Panda, the planar arms), the position turned for a point robot. Checked on the sphere centres; a robot that is
    neither is refused by name. The result may leave the joint limits (see :func:`for_scene`)."""
    import torch

    from mpd.envs.primitives import rot_z

    robot, dim = task.robot, task.robot.task_dim
    rz = rot_z(rotation_deg, dim)

    def position(x: np.ndarray) -> np.ndarray:
        return x @ rz.T

    def first_joint(x: np.ndarray) -> np.ndarray:
        out = x.copy()
        out[:, 0] += np.deg2rad(rotation_deg)
        return out

    rules = ([position] if robot.dof == dim else []) + [first_joint]
    probe = robot.random_q(16, torch.Generator().manual_seed(0)).numpy()
    want = robot.sphere_centres(torch.as_tensor(probe)).numpy() @ rz.T
    for rule in rules:
        if np.allclose(robot.sphere_centres(torch.as_tensor(rule(probe))).numpy(), want, atol=1e-6):
            return rule(np.asarray(q, dtype=np.float64))
    raise ValueError(
        f"{task.name}: robot {robot.name} cannot turn its contexts with the scene (neither its first joint nor its "
        "position turns it about the base z axis): set turn_contexts = false"
    )


def _turned(base: ContextSet, task: Task, rotation_deg: float) -> dict[str, np.ndarray]:
    from mpd.envs.primitives import rot_z

    arrays = base.arrays()
    arrays["q_start"] = turn_configurations(task, base.q_start, rotation_deg).astype(base.q_start.dtype)
    arrays["q_goal"] = turn_configurations(task, base.q_goal, rotation_deg).astype(base.q_goal.dtype)
    if base.ee_pos is not None:
        r = rot_z(rotation_deg, 3)
        arrays["ee_pos"] = base.ee_pos @ r.T.astype(base.ee_pos.dtype)
        arrays["ee_rot"] = (r.astype(base.ee_rot.dtype) @ base.ee_rot).astype(base.ee_rot.dtype)
    return arrays


def for_scene(
    base: ContextSet, task: Task, extra_objects: bool, rotation_deg: float = 0.0, turn: bool = False
) -> ContextSet:
    """The task's contexts that are valid in a scene (start and goal, with the clearance); the others are skipped.

    ``turn`` (a spec's ``turn_contexts``): in a rotated scene, the contexts turn with it (start and goal configurations
    by :func:`turn_configurations`, the goal pose by the same rotation), so each is its training-scene problem turned
    about the base, and only a change of the prior's inputs remains; a context whose turned start or goal leaves the
    joint limits is skipped. Without it (the default) the contexts stay where they are and the obstacles turn."""
    scene = scene_name(extra_objects, rotation_deg)
    turned = bool(turn and rotation_deg)
    arrays = _turned(base, task, rotation_deg) if turned else base.arrays()
    if not extra_objects and not rotation_deg:
        keep = np.ones(len(base), dtype=bool)
    else:
        keep = _ends_valid(task, arrays["q_start"], arrays["q_goal"], extra_objects, rotation_deg)
    n_out = 0
    if turned:
        import torch

        inside = (
            task.robot.within_limits(torch.as_tensor(arrays["q_start"])).numpy()
            & task.robot.within_limits(torch.as_tensor(arrays["q_goal"])).numpy()
        )
        n_out = int((~inside).sum())
        keep &= inside
    arrays = {k: v[keep] for k, v in arrays.items()}
    meta = dict(base.meta, scene=scene, n_contexts=int(keep.sum()), n_skipped=int((~keep).sum()))
    meta["skipped_index"] = base.index[~keep].tolist()
    if turned:
        meta["turned"] = True
        meta["n_outside_limits"] = n_out
    return finalize(ContextSet.from_arrays(task.name, scene, arrays, meta))


def sampled_contexts(task: Task, n: int, extra_objects: bool, rotation_deg: float = 0.0) -> ContextSet:
    """mpd's earlier protocol (``source = "sampled"``): the same dataset-independent contexts in every scene."""
    from mpd.data.contexts import evaluation_contexts

    if rotation_deg:
        raise ValueError("sampled contexts are defined for the unrotated scenes only; use source = 'held-out'")
    ec = evaluation_contexts(task, n)
    meta = {
        "source": "sampled",
        "task": task.name,
        "scene": scene_name(extra_objects, rotation_deg),
        "n_contexts": n,
        "n_skipped": 0,
        "skipped_index": [],
    }
    cs = ContextSet(
        task.name,
        meta["scene"],
        ec.q_start,
        ec.q_goal,
        np.arange(n, dtype=np.int64),
        -np.ones(n, dtype=np.int64),
        ec.ee_pos,
        ec.ee_rot,
        meta,
    )
    return finalize(cs)


def finalize(cs: ContextSet) -> ContextSet:
    """Hash the set and store it (once) under the cache; returns it with ``meta['sha256']`` and ``meta['path']``."""
    arrays = cs.arrays()
    sha = arrays_sha256(arrays)
    cs.meta["sha256"] = sha
    path = contexts_dir() / f"{cs.task}-{cs.scene}-{sha[:16]}.npz"
    cs.meta["path"] = str(path)
    if path.exists():
        try:
            load_context_file(path)
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):  # damaged: written again below
            path.unlink()
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
        side = path.with_suffix(".json")
        tmpj = side.with_name(f".{side.name}.tmp{os.getpid()}")
        tmpj.write_text(json.dumps({k: v for k, v in cs.meta.items() if k != "path"}, indent=1))
        os.replace(tmpj, side)
    return cs


def contexts_dir() -> Path:
    return cache_dir() / "contexts"


def load_context_file(path: str | Path) -> ContextSet:
    """A stored set, verified against the hash in its name and sidecar."""
    path = Path(path)
    try:
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
    except (EOFError, KeyError, zipfile.BadZipFile) as e:
        raise ValueError(f"context file {path} does not read back ({type(e).__name__}: {e})") from None
    meta = json.loads(path.with_suffix(".json").read_text()) if path.with_suffix(".json").exists() else {}
    sha = arrays_sha256(arrays)
    if not path.stem.endswith(sha[:16]) or meta.get("sha256", sha) != sha:
        raise ValueError(f"context file {path} does not match its hash (corrupted or edited): sha256 {sha[:16]}")
    meta.update(sha256=sha, path=str(path))
    return ContextSet.from_arrays(meta.get("task", path.stem.rsplit("-", 2)[0]), meta.get("scene", ""), arrays, meta)


def list_context_files(task: str | None = None) -> list[ContextSet]:
    out = []
    for p in sorted(contexts_dir().glob("*.npz")):
        if p.name.startswith(".") or (task and not p.name.startswith(f"{task}-")):
            continue
        if not p.with_suffix(".json").exists():
            continue  # the dataset-independent generator's own cache files
        try:
            out.append(load_context_file(p))
        except (ValueError, OSError, KeyError):
            continue
    return out
