"""Loading a generated dataset: verified chunks -> one :class:`Dataset` of paths (forward and reversed).

Only contexts whose planning succeeded and whose B-spline fit stayed within twice the joint range are kept;
the failures stay in the chunks and in ``info["figures"]``. The reversed copies (the paper's "additional path
by reverse-connecting"; the authors reverse the path, "Paper vs code" 12) are built here and appended after
the forward paths. A clamped uniform B-spline reversed in time is the same spline with its control points in
reverse order, so the reversed fits are exact.

Split. Contexts, not paths, are split (a seeded permutation of the context ids), so both directions of a
context land in the same split. The authors split by path id after doubling, so the reversed copy of a
held-out path can be in the training set.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpd.data.definition import ResolvedDefinition, load_definition
from mpd.data.planning import problem_seed
from mpd.data.storage import read_chunk, read_sidecar

SPLITS = ("train", "val", "test")


@dataclass
class Dataset:
    """All stored paths of a dataset (P = 2 x kept contexts), numpy arrays over paths."""

    name: str
    task: str
    q_start: np.ndarray  # (P, dof) float64
    q_goal: np.ndarray  # (P, dof) float64
    paths: np.ndarray  # (P, n_points, dof) float32
    control_points: np.ndarray  # (P, n_control_points, dof) float32
    fit_free: np.ndarray  # (P,) the fitted B-spline is collision free (sphere model, training scene, margin 0)
    context_id: np.ndarray  # (P,) int64
    reversed: np.ndarray  # (P,) bool
    split: np.ndarray  # (P,) int8, index into SPLITS
    plan_time: np.ndarray  # (P,) s (of the planned forward path)
    ee_pos: np.ndarray | None = None  # (P, 3) goal pose = FK(q_goal), end-effector-goal tasks
    ee_rot: np.ndarray | None = None  # (P, 3, 3)
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.q_start)

    def subset(self, which: str | np.ndarray) -> Dataset:
        """The paths of one split (``train``/``val``/``test``) or of a boolean/index selection."""
        sel = self.split == SPLITS.index(which) if isinstance(which, str) else np.asarray(which)
        arrays = {
            k: (v[sel] if isinstance(v, np.ndarray) else v)
            for k, v in self.__dict__.items()
            if k not in ("name", "task", "info")
        }
        return Dataset(self.name, self.task, info=self.info, **arrays)


def split_of_contexts(n_contexts: int, seed: int, val: float, test: float) -> np.ndarray:
    """Split (index into SPLITS) of every context id: a seeded permutation, test first, then val."""
    perm = np.random.default_rng(problem_seed(seed, "split")).permutation(n_contexts)
    n_test, n_val = int(round(test * n_contexts)), int(round(val * n_contexts))
    out = np.zeros(n_contexts, dtype=np.int8)
    out[perm[:n_test]] = 2
    out[perm[n_test : n_test + n_val]] = 1
    return out


def load_dataset(
    name_or_path: str | Path | ResolvedDefinition,
    generate_missing: bool = True,
    workers: int | None = None,
    progress: bool = True,
    create_lock: bool = True,
    executor: str = "local",
    address: str | None = None,
) -> Dataset:
    """Load a dataset by name (``datasets/NAME.toml``) or definition path (``create_lock``: see
    :func:`mpd.data.generate.generate`).

    Every chunk is verified against its recorded sha256 (and the lock file's, when it describes this
    identity); a missing, partial or corrupted chunk is reported and regenerated, never used.
    """
    from mpd.data.generate import chunk_states, generate

    rd = name_or_path if isinstance(name_or_path, ResolvedDefinition) else load_definition(name_or_path)
    bad = chunk_states(rd)
    if bad:
        n_missing = sum(why == "missing" for why in bad.values())
        if not generate_missing:
            raise FileNotFoundError(
                f"dataset {rd.name}: {len(bad)} of {rd.definition.n_chunks} chunks are not usable "
                f"({n_missing} missing); run `mpd data generate {rd.path or rd.name}`"
            )
        if n_missing == rd.definition.n_chunks:
            print(
                f"{rd.name}: not generated yet, generating {rd.definition.n_contexts} contexts",
                file=sys.stderr,
            )
        generate(rd, workers=workers, progress=progress, create_lock=create_lock, executor=executor, address=address)
        still = chunk_states(rd, use_lock=False)
        if still:
            raise RuntimeError(f"dataset {rd.name}: chunks {sorted(still)} could not be generated")
    return _assemble(rd)


def _assemble(rd: ResolvedDefinition) -> Dataset:
    d, task = rd.definition, rd.task
    chunks = [read_chunk(rd.data_dir, i) for i in range(d.n_chunks)]
    plan_time = np.concatenate([np.asarray(read_sidecar(rd.data_dir, i)["plan_time"]) for i in range(d.n_chunks)])
    cat = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    keep = cat["success"] & cat["fit_in_range"]
    ids = cat["context_id"][keep]
    split = split_of_contexts(d.n_contexts, d.seed, d.split.val, d.split.test)[ids]
    qs, qg = cat["q_start"][keep], cat["q_goal"][keep]
    paths, cps = cat["path"][keep], cat["control_points"][keep]
    n = len(ids)
    ds = Dataset(
        name=rd.name,
        task=task.name,
        q_start=np.concatenate([qs, qg]),
        q_goal=np.concatenate([qg, qs]),
        paths=np.concatenate([paths, paths[:, ::-1]]),
        control_points=np.concatenate([cps, cps[:, ::-1]]),
        fit_free=np.concatenate([cat["fit_free"][keep]] * 2),
        context_id=np.concatenate([ids, ids]),
        reversed=np.repeat([False, True], n),
        split=np.concatenate([split, split]),
        plan_time=np.concatenate([plan_time[keep]] * 2),
    )
    if task.ee_goal:
        from mpd.data.contexts import ee_goal_pose

        p_start, r_start = ee_goal_pose(task, qs) if n else (np.zeros((0, 3)), np.zeros((0, 3, 3)))
        ds.ee_pos = np.concatenate([cat["ee_pos"][keep], p_start])
        ds.ee_rot = np.concatenate([cat["ee_rot"][keep], r_start])
    try:
        lock = json.loads((rd.data_dir / "lock.json").read_text())
    except FileNotFoundError:
        lock = {}
    ds.info = {
        "identity": rd.identity,
        "data_dir": str(rd.data_dir),
        "content_hash": lock.get("content_hash"),
        "chunks": lock.get("outs"),
        "figures": lock.get("figures"),
        "definition": lock.get("definition"),
        "task_sha256": task.file_hash,
    }
    return ds
