"""Shipped priors: trained checkpoints committed with the code, found by model identity and verified by hash.

A fresh clone evaluates at once: when :func:`mpd.models.train.train_model` looks for a model that is not in the
cache, it first looks here for a file of the same identity (dataset content hash, kind, parametrization and its
settings, network and training specs, seed, network version), checks its sha256 against its lock file and copies it
into the cache. A file whose hash does not match its lock is never used: it is named on stderr and the model is
trained. ``mpd train --no-shipped`` trains (and so reproduces) a shipped model instead.

Layout, one folder per task under ``models/`` (the dataset digests, :mod:`mpd.data.digest`, sit in
``mpd/priors/<task>/``)::

    mpd/priors/models/<task>/<kind>-<parametrization>-<identity>.pt
    mpd/priors/models/<task>/<kind>-<parametrization>-<identity>.lock.json

A folder of ``MPD_PRIORS`` may also hold them one level up (``<folder>/<task>/``), the layout before 2026-12-04.

The file is a checkpoint of the cache format with the EMA weights only (what sampling uses: ``weights`` refers to
the same tensors, which ``torch.save`` stores once), float32, so that a shipped prior samples exactly what the
trained one does; or, where float32 would exceed the size limit (the Panda-sized networks, ~18 MB), rounded to
bfloat16 (``weights_dtype``, recorded in the lock; loading casts them back to float32, so only the weights'
rounding differs from the trained model: ``tests/test_models.py`` bounds its effect on a denoising step, and the
closing notes compare the samples). The lock holds the file's sha256 and size, and what made it: task and dataset
hashes, training settings, seed, steps, training wall time, CPU, device and code commit. ``MPD_PRIORS`` (folders
separated by ``os.pathsep``) is searched before the bundled folder; ``MPD_PRIORS=none`` turns shipped priors off.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import torch

from mpd.models.checkpoint import META_FILE, MODEL_FILE, checkpoint_meta, read_checkpoint
from mpd.paths import SHIPPED_BUNDLED, SHIPPED_ENV, shipped_roots
from mpd.provenance import cpu_model
from mpd.schema import file_sha256

BUNDLED = SHIPPED_BUNDLED
ENV = SHIPPED_ENV
LOCK_FORMAT = "mpd-shipped-prior"
MAX_BYTES = 10 * 1024 * 1024  # the size budget: <= 5 MB for the 2-D tasks, <= 10 MB for the Panda ones
MODELS = "models"  # the sub-folder of a root that holds the checkpoints


def _task_dirs(root: Path, task_name: str) -> tuple[Path, Path]:
    """Where a root keeps a task's shipped checkpoints: ``root/models/<task>``, then the older ``root/<task>``."""
    return root / MODELS / task_name, root / task_name


def roots() -> list[Path]:
    """The folders searched for shipped priors, in order (:func:`mpd.paths.shipped_roots`)."""
    return shipped_roots()


def stem(kind: str, parametrization: str, identity: str) -> str:
    return f"{kind}-{parametrization}-{identity}"


def _lock_path(path: Path) -> Path:
    return path.with_name(path.name[: -len(".pt")] + ".lock.json")


def verify(path: Path) -> tuple[dict[str, Any] | None, str | None]:
    """(lock, None) when ``path`` matches its lock file, else (lock or None, why not)."""
    lock_path = _lock_path(path)
    if not lock_path.is_file():
        return None, f"no lock file {lock_path.name}"
    try:
        lock = json.loads(lock_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        return None, f"unreadable lock file {lock_path}: {e}"
    if lock.get("format") != LOCK_FORMAT:
        return lock, f"{lock_path} is not a shipped-prior lock (format {lock.get('format')!r})"
    size = path.stat().st_size
    if size != lock.get("size"):
        return lock, f"size {size} bytes, its lock says {lock.get('size')}"
    digest = file_sha256(path)
    if digest != lock.get("sha256"):
        return lock, f"sha256 {digest[:16]}…, its lock says {str(lock.get('sha256'))[:16]}…"
    return lock, None


def find(task_name: str, kind: str, parametrization: str, identity: str) -> Path | None:
    """The verified shipped file of this model, or None. A corrupted one is reported and skipped."""
    name = stem(kind, parametrization, identity) + ".pt"
    for path in (d / name for root in roots() for d in _task_dirs(root, task_name)):
        if not path.is_file():
            continue
        lock, why = verify(path)
        if why is None and lock.get("identity") == identity:
            return path
        why = why or f"its lock is for identity {lock.get('identity')!r}"
        print(f"mpd: shipped prior {path} is not used ({why}); the model will be trained", file=sys.stderr)
    return None


def install(task_name: str, kind: str, parametrization: str, identity: str, dest_dir: Path) -> Path | None:
    """Copy the verified shipped file of this model to ``dest_dir/model.pt`` (with its ``meta.json``); None when
    there is none. The copy is checked against the lock again, so a file changed under us is not used either."""
    src = find(task_name, kind, parametrization, identity)
    if src is None:
        return None
    dest_dir.mkdir(parents=True, exist_ok=True)
    lock = json.loads(_lock_path(src).read_text())
    tmp = dest_dir / f".{MODEL_FILE}.shipped-{os.getpid()}"
    shutil.copyfile(src, tmp)
    if file_sha256(tmp) != lock["sha256"]:
        tmp.unlink(missing_ok=True)
        print(
            f"mpd: the copy of shipped prior {src} does not match its lock; the model will be trained", file=sys.stderr
        )
        return None
    meta = checkpoint_meta(read_checkpoint(tmp))
    meta.update(
        source="shipped",
        shipped_file=str(src),
        shipped_sha256=lock["sha256"],
        **{k: lock.get(k) for k in ("n_train", "n_val", "n_parameters", "device", "steps_per_s", "cpu")},
        final_train_loss=lock.get("final_train_loss"),
        final_val_loss=lock.get("final_val_loss"),
        created=lock.get("created"),
    )
    meta_tmp = dest_dir / f".{META_FILE}.tmp-{os.getpid()}"
    meta_tmp.write_text(json.dumps(meta, indent=2, sort_keys=True))
    os.replace(meta_tmp, dest_dir / META_FILE)  # meta first: a model.pt always has its meta.json
    os.replace(tmp, dest_dir / MODEL_FILE)
    return dest_dir / MODEL_FILE


WEIGHTS_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}


def ship(
    model_path: str | Path, root: str | Path = BUNDLED, max_bytes: int = MAX_BYTES, weights_dtype: str = "auto"
) -> Path:
    """Write the shipped form of a trained cache model (its ``model.pt``) and its lock under ``root/models/<task>/``;
    returns the shipped file. ``weights_dtype``: float32, bfloat16, or auto (float32 when it fits in ``max_bytes``,
    else bfloat16). Raises ValueError when the file would exceed ``max_bytes``."""
    if weights_dtype not in ("auto", *WEIGHTS_DTYPES):
        raise ValueError(f"weights_dtype {weights_dtype!r}: expected auto, {', '.join(WEIGHTS_DTYPES)}")
    model_path = Path(model_path)
    if model_path.is_dir():
        model_path = model_path / MODEL_FILE
    ckpt = read_checkpoint(model_path)
    ckpt.pop("_path", None)
    meta_path = model_path.parent / META_FILE
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    ema32 = ckpt["ema_weights"]
    ckpt["weights_are_ema"] = True
    out_dir = Path(root) / MODELS / ckpt["task_name"]
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / (stem(ckpt["kind"], ckpt["parametrization"], ckpt["identity"]) + ".pt")
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    for dtype in ("float32", "bfloat16") if weights_dtype == "auto" else (weights_dtype,):
        want = WEIGHTS_DTYPES[dtype]
        ema = {k: v.to(want) if v.is_floating_point() else v for k, v in ema32.items()}
        ckpt["ema_weights"] = ckpt["weights"] = ema  # the same tensors: stored once
        ckpt["weights_dtype"] = dtype
        torch.save(ckpt, tmp)
        size = tmp.stat().st_size
        if size <= max_bytes:
            break
    else:
        tmp.unlink()
        raise ValueError(
            f"{model_path}: the shipped file would be {size / 2**20:.1f} MB in {dtype} (limit {max_bytes / 2**20:.0f})"
        )
    os.replace(tmp, path)
    prov = ckpt.get("provenance") or {}
    lock = {
        "format": LOCK_FORMAT,
        "file": path.name,
        "sha256": file_sha256(path),
        "size": size,
        "identity": ckpt["identity"],
        "task_name": ckpt["task_name"],
        "task_hash": ckpt["task_hash"],
        "dataset_hash": ckpt["dataset_hash"],
        "kind": ckpt["kind"],
        "parametrization": ckpt["parametrization"],
        "parametrization_settings": ckpt["parametrization_settings"],
        "model_spec": ckpt["model_spec"],
        "training_spec": ckpt["training_spec"],
        "seed": ckpt["seed"],
        "steps": int(ckpt["step"]),
        "weights_dtype": ckpt["weights_dtype"],
        "wall_time_s": float(ckpt.get("wall_time_s", 0.0)),
        "resumed_from_trunk_step": ckpt.get("resumed_from_trunk_step"),
        "started_from": ckpt.get("started_from"),  # mpd train --from: the checkpoint of another budget
        "init_from": ckpt.get("init_from"),  # mpd train --init-from: the weights it started from (identity too)
        "execution": ckpt.get("execution"),  # None: eager throughout (mpd.models.train, compile_step)
        "cpu": meta.get("cpu") or cpu_model(),
        "device": meta.get("device"),
        "n_train": meta.get("n_train"),
        "n_val": meta.get("n_val"),
        "n_parameters": meta.get("n_parameters"),
        "steps_per_s": meta.get("steps_per_s"),
        "final_train_loss": meta.get("final_train_loss"),
        "final_val_loss": meta.get("final_val_loss"),
        "git_commit": prov.get("git_commit"),
        "git_dirty": prov.get("git_dirty"),
        "libraries": prov.get("libraries"),
        "created": meta.get("created"),
        "shipped": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    lock_path = _lock_path(path)
    tmp_lock = lock_path.with_name(f".{lock_path.name}.tmp-{os.getpid()}")
    tmp_lock.write_text(json.dumps(lock, indent=2, sort_keys=True) + "\n")
    os.replace(tmp_lock, lock_path)
    return path


def list_shipped() -> list[dict[str, Any]]:
    """Every shipped prior with its lock and whether it verifies (``ok``, ``problem``)."""
    out = []
    for root in roots():
        for path in sorted([*root.glob(f"{MODELS}/*/*.pt"), *root.glob("*/*.pt")]):
            lock, why = verify(path)
            out.append({**(lock or {}), "path": str(path), "ok": why is None, "problem": why})
    return out


__all__ = ["BUNDLED", "ENV", "find", "install", "list_shipped", "roots", "ship", "verify"]
