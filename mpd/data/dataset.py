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
from mpd.data.storage import map_chunk, read_sidecar

SPLITS = ("train", "val", "test")


@dataclass
class Dataset:
    """All stored paths of a dataset (P = 2 x kept contexts), numpy arrays over paths."""

    name: str
    task: str
    q_start: np.ndarray  # (P, dof) float64
    q_goal: np.ndarray  # (P, dof) float64
    paths: PathArray | np.ndarray  # (P, n_points, dof) float32: read from the chunks where indexed (PathArray)
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
            k: (v[sel] if isinstance(v, np.ndarray) else v.take(sel) if isinstance(v, PathArray) else v)
            for k, v in self.__dict__.items()
            if k not in ("name", "task", "info")
        }
        return Dataset(self.name, self.task, info=self.info, **arrays)


class PathArray:
    """The dense paths of a dataset without holding them: rows are read from the memory-mapped chunks where they are
    indexed (``ds.paths[i]``, ``ds.paths[mask]``, ``ds.paths[:, 0]``, ``blocks``), so that loading a paper-size
    dataset (EnvSpheres3D: 2 M paths, ~7 GB as float32) costs no more memory than its contexts and control points.
    Row r < n is forward path r; row n + r is its reversed copy. ``np.asarray(paths)`` reads them all."""

    def __init__(self, chunks: list[np.ndarray], keep: list[np.ndarray], rows: np.ndarray | None = None):
        self._chunks = chunks  # per chunk: its (contexts, n_points, dof) "path" member, memory-mapped
        self._keep = keep  # per chunk: the rows kept (success and a fit in range)
        sizes = np.array([len(k) for k in keep], dtype=np.int64)
        self._n_fwd = int(sizes.sum())
        self._chunk_of = np.repeat(np.arange(len(keep), dtype=np.int32), sizes)
        self._row_of = np.concatenate(keep).astype(np.int64) if keep else np.zeros(0, dtype=np.int64)
        self._rows = np.arange(2 * self._n_fwd, dtype=np.int64) if rows is None else rows
        first = next((c for c in chunks if len(c)), None)
        self._tail = tuple(first.shape[1:]) if first is not None else (0, 0)
        self.dtype = first.dtype if first is not None else np.dtype(np.float32)

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self._rows), *self._tail)

    @property
    def ndim(self) -> int:
        return 3

    def __len__(self) -> int:
        return len(self._rows)

    def take(self, sel) -> PathArray:
        """The rows ``sel`` (an index array or a boolean mask), still unread."""
        out = object.__new__(PathArray)
        out.__dict__.update(self.__dict__)
        out._rows = self._rows[sel]
        return out

    def _read(self, rows: np.ndarray) -> np.ndarray:
        fwd = rows % self._n_fwd if self._n_fwd else rows
        out = np.empty((len(rows), *self._tail), dtype=self.dtype)
        chunk = self._chunk_of[fwd]
        for c in np.unique(chunk):
            sel = np.flatnonzero(chunk == c)
            local = self._row_of[fwd[sel]]  # rows within chunk c
            order = np.argsort(local, kind="stable")  # ascending reads of the mapped file
            out[sel[order]] = self._chunks[c][local[order]]
        rev = rows >= self._n_fwd
        out[rev] = out[rev, ::-1]
        return out

    def __getitem__(self, key):
        first, rest = (key[0], key[1:]) if isinstance(key, tuple) else (key, ())
        rows = self._rows[first]
        if np.ndim(rows) == 0:
            out = self._read(np.array([rows]))[0]
            return out[rest] if rest else out
        out = self._read(np.asarray(rows))
        return out[(slice(None), *rest)] if rest else out

    def __array__(self, dtype=None, copy=None):
        out = self._read(self._rows)
        return out if dtype is None else out.astype(dtype)

    def blocks(self, size: int = 10_000):
        """(start, stop, paths[start:stop]) over all rows, ``size`` at a time."""
        for start in range(0, len(self), size):
            stop = min(start + size, len(self))
            yield start, stop, self._read(self._rows[start:stop])


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
    # memory-mapped: every field but the dense paths is gathered (contexts, control points, flags); the paths stay
    # in the chunk files and are read where they are indexed (PathArray)
    chunks = [map_chunk(rd.data_dir, i) for i in range(d.n_chunks)]
    sides = [read_sidecar(rd.data_dir, i) for i in range(d.n_chunks)]
    synthetic = any(side.get("synthetic") for side in sides)
    if synthetic:
        print(f"{rd.name}: SYNTHETIC data (random paths, for measurements only)", file=sys.stderr)
    keep_per_chunk = [np.flatnonzero(np.asarray(c["success"]) & np.asarray(c["fit_in_range"])) for c in chunks]
    n = int(sum(len(k) for k in keep_per_chunk))

    def both(field: str, swap: str | None = None, reverse: bool = False, dtype=None) -> np.ndarray:
        """The kept rows of ``field``, forward then the reversed copies, filled chunk by chunk into one array (no
        full-size intermediate: a paper-size dataset's control points are ~2 GB)."""
        first = chunks[0][field]
        out = np.empty((2 * n, *first.shape[1:]), dtype=dtype or first.dtype)
        o = 0
        for c, k in zip(chunks, keep_per_chunk):
            out[o : o + len(k)] = c[field][k]
            out[n + o : n + o + len(k)] = (c[swap] if swap else c[field])[k]
            o += len(k)
        if reverse:
            out[n:] = out[n:, ::-1]
        return out

    ids = both("context_id")
    split = split_of_contexts(d.n_contexts, d.seed, d.split.val, d.split.test)[ids]
    kept_plan = np.concatenate([np.asarray(side["plan_time"])[k] for side, k in zip(sides, keep_per_chunk)])
    ds = Dataset(
        name=rd.name,
        task=task.name,
        q_start=both("q_start", swap="q_goal"),
        q_goal=both("q_goal", swap="q_start"),
        paths=PathArray([c["path"] for c in chunks], keep_per_chunk),
        control_points=both("control_points", reverse=True),
        fit_free=both("fit_free"),
        context_id=ids,
        reversed=np.repeat([False, True], n),
        split=split,
        plan_time=np.concatenate([kept_plan] * 2),
    )
    if task.ee_goal:
        from mpd.data.contexts import ee_goal_pose

        # the reversed copies' goal pose is FK of the forward start, in blocks (FK keeps every link's frame)
        ds.ee_pos, ds.ee_rot = both("ee_pos"), both("ee_rot")
        for a in range(0, n, 50_000):
            b = min(a + 50_000, n)
            ds.ee_pos[n + a : n + b], ds.ee_rot[n + a : n + b] = ee_goal_pose(task, ds.q_start[a:b])
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
        "synthetic": synthetic,
    }
    return ds
