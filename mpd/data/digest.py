"""Dataset digests: what an evaluation takes from a dataset, shipped next to the priors, so that a fresh clone with
shipped priors evaluates without generating the dataset (EnvNarrowPassageDense2D's 10k paths take ~22 min here).

An evaluation reads three things from a task's dataset:

* its **content hash**, which is in the identity of every model trained on it;
* the **range** (per joint lo, hi) of the training split's free B-spline control points: the normalized space of
  the planners without a model (:func:`mpd.experiments.artifacts.data_range`);
* the **held-out forward paths** its contexts come from (:mod:`mpd.data.eval_contexts`).

A digest holds exactly these. Its held-out rows are the dataset's forward rows of the ``test`` and ``val`` splits, in
dataset order, so :func:`mpd.data.eval_contexts.task_contexts` gives the same contexts from the digest as from the
dataset, for every context seed and every number of contexts (tested). Layout, beside the shipped priors::

    <root>/<task>/dataset-<dataset name>-<content hash[:16]>.npz    the held-out rows
    <root>/<task>/dataset-<dataset name>-<content hash[:16]>.json   sha256 of the .npz, range, identity, provenance

A digest whose ``.npz`` does not match the sha256 of its ``.json`` is named on stderr and not used (the runner then
generates the dataset). The runner uses a digest only when the dataset is not in the cache and every model the run
needs of that task is in the cache or shipped: anything to train needs the dataset itself.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpd.data.storage import npz_bytes, write_atomic
from mpd.paths import shipped_roots
from mpd.schema import file_sha256

FORMAT = "mpd-dataset-digest"
ARRAYS = ("q_start", "q_goal", "context_id", "split", "ee_pos", "ee_rot")


@dataclass
class Digest:
    """The held-out forward rows of a dataset with the attributes :mod:`mpd.data.eval_contexts` reads from a
    :class:`mpd.data.dataset.Dataset` (``name``, ``info``, ``split``, ``reversed``, ``q_start``, ...)."""

    name: str
    task: str
    q_start: np.ndarray
    q_goal: np.ndarray
    context_id: np.ndarray
    split: np.ndarray
    data_range: tuple[list[float], list[float]]
    ee_pos: np.ndarray | None = None
    ee_rot: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    path: Path | None = None

    @property
    def reversed(self) -> np.ndarray:
        return np.zeros(len(self.q_start), dtype=bool)  # forward rows only

    def __len__(self) -> int:
        return len(self.q_start)


def stem(dataset_name: str, content_hash: str) -> str:
    return f"dataset-{dataset_name}-{content_hash[:16]}"


def write(task, dataset, data_range: tuple[list[float], list[float]], root: str | Path) -> Path:
    """Write the digest of a loaded dataset under ``root/<task>/``; returns the ``.npz`` path."""
    from mpd.data.dataset import SPLITS
    from mpd.data.eval_contexts import HELD_OUT
    from mpd.provenance import provenance

    content = dataset.info.get("content_hash")
    if not content:
        raise ValueError(f"dataset {dataset.name}: no content hash (its lock.json is missing): generate it first")
    held = np.isin(dataset.split, [SPLITS.index(s) for s in HELD_OUT]) & ~dataset.reversed
    arrays = {
        "q_start": dataset.q_start[held],
        "q_goal": dataset.q_goal[held],
        "context_id": dataset.context_id[held].astype(np.int64),
        "split": dataset.split[held],
    }
    if task.ee_goal:
        arrays["ee_pos"], arrays["ee_rot"] = dataset.ee_pos[held], dataset.ee_rot[held]
    out_dir = Path(root) / task.name
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / (stem(dataset.name, content) + ".npz")
    write_atomic(path, npz_bytes(arrays))  # fixed zip timestamps: the same dataset gives the same bytes
    lo, hi = data_range
    record = {
        "format": FORMAT,
        "file": path.name,
        "sha256": file_sha256(path),
        "size": path.stat().st_size,
        "task_name": task.name,
        "task_hash": task.file_hash,
        "dataset": dataset.name,
        "dataset_identity": dataset.info.get("identity"),
        "content_hash": content,
        "n_held_out": int(held.sum()),
        "n_paths": int(len(dataset)),
        "data_range": {"lo": [float(v) for v in lo], "hi": [float(v) for v in hi]},
        "provenance": provenance(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    side = path.with_suffix(".json")
    tmpj = side.with_name(f".{side.name}.tmp-{os.getpid()}")
    tmpj.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    os.replace(tmpj, side)
    return path


def load(path: str | Path) -> Digest:
    """A digest, verified against its ``.json``; ValueError naming the file when it does not match."""
    path = Path(path)
    side = path.with_suffix(".json")
    try:
        record = json.loads(side.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"dataset digest {path}: unreadable {side.name}: {e}") from e
    if record.get("format") != FORMAT:
        raise ValueError(f"dataset digest {side}: not a digest (format {record.get('format')!r})")
    sha = file_sha256(path)
    if sha != record.get("sha256"):
        raise ValueError(f"dataset digest {path}: sha256 {sha[:16]}…, its {side.name} says {record.get('sha256')}")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    info = {
        "identity": record.get("dataset_identity"),
        "content_hash": record["content_hash"],
        "task_sha256": record.get("task_hash"),
        "digest": str(path),
        "digest_sha256": sha,
    }
    rng = record["data_range"]
    return Digest(
        name=record["dataset"],
        task=record["task_name"],
        q_start=arrays["q_start"],
        q_goal=arrays["q_goal"],
        context_id=arrays["context_id"],
        split=arrays["split"],
        data_range=(list(rng["lo"]), list(rng["hi"])),
        ee_pos=arrays.get("ee_pos"),
        ee_rot=arrays.get("ee_rot"),
        info=info,
        path=path,
    )


def find(task_name: str, dataset_name: str, content_hash: str | None) -> Digest | None:
    """The verified digest of this dataset content, or None; a corrupted one is named on stderr and skipped."""
    if not content_hash:
        return None
    for root in shipped_roots():
        path = root / task_name / (stem(dataset_name, content_hash) + ".npz")
        if not path.is_file():
            continue
        try:
            dg = load(path)
        except ValueError as e:
            print(f"mpd: {e}; not used", file=sys.stderr)
            continue
        if dg.info["content_hash"] == content_hash:
            return dg
    return None


__all__ = ["Digest", "find", "load", "write"]
