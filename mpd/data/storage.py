"""Chunk files of a dataset: byte-reproducible ``.npz`` archives and their JSON sidecars.

A chunk holds a fixed range of context indices. Its ``.npz`` holds only deterministic content (contexts,
paths, control points, flags), written as an uncompressed zip with fixed timestamps so that the same data
gives the same bytes (and sha256) on every machine; ``numpy.savez`` stamps the current time into the archive.
The sidecar ``chunk-NNNNN.json`` records the chunk's sha256 and size and what varies from run to run (planning
times, wall time). Both are written to a temporary name and renamed, the archive first: a chunk counts as
finished only when its sidecar exists and the archive's sha256 matches it.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np

from mpd.schema import file_sha256

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def chunk_name(i: int) -> str:
    return f"chunk-{i:05d}.npz"


def sidecar_name(i: int) -> str:
    return f"chunk-{i:05d}.json"


def _tmp(path: Path) -> Path:
    return path.with_name(f"{path.name}.tmp-{os.getpid()}")


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An ``np.load``-able archive whose bytes depend only on the arrays (names in the given order)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, a in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
            info.external_attr = 0o644 << 16
            b = io.BytesIO()
            np.lib.format.write_array(b, np.ascontiguousarray(a), allow_pickle=False)
            zf.writestr(info, b.getvalue())
    return buf.getvalue()


def write_atomic(path: Path, data: bytes) -> None:
    tmp = _tmp(path)
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def chunk_record(i: int, data: bytes, meta: dict) -> dict:
    """The sidecar record of chunk i whose archive bytes are ``data``."""
    record = {
        "chunk": i,
        "path": chunk_name(i),
        "sha256": hashlib.sha256(data).hexdigest(),
        "size": len(data),
    }
    record.update(meta)
    return record


def write_chunk_bytes(directory: Path, i: int, data: bytes, record: dict) -> dict:
    """Write chunk i from its archive bytes and sidecar record (archive, then sidecar: a chunk counts as finished
    only once its sidecar exists)."""
    write_atomic(directory / chunk_name(i), data)
    write_atomic(directory / sidecar_name(i), (json.dumps(record, indent=1) + "\n").encode())
    return record


def write_chunk(directory: Path, i: int, arrays: dict[str, np.ndarray], meta: dict) -> dict:
    """Write chunk i (archive, then sidecar); returns the sidecar record."""
    data = npz_bytes(arrays)
    return write_chunk_bytes(directory, i, data, chunk_record(i, data, meta))


def read_sidecar(directory: Path, i: int) -> dict | None:
    p = directory / sidecar_name(i)
    try:
        return json.loads(p.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def verify_chunk(directory: Path, i: int, expected_sha256: str | None = None) -> tuple[bool, str]:
    """(finished, why not): the archive exists, its sha256 matches its sidecar (and ``expected_sha256``)."""
    side = read_sidecar(directory, i)
    path = directory / chunk_name(i)
    if not path.exists():
        return False, "missing" if side is None else "archive missing"
    if side is None:
        return False, "no sidecar (interrupted while writing)"
    size = path.stat().st_size
    if size != side.get("size"):
        return False, f"size {size} bytes, expected {side.get('size')} (truncated or corrupted)"
    sha = file_sha256(path)
    if sha != side.get("sha256"):
        return (
            False,
            f"sha256 {sha[:12]}... does not match its record {str(side.get('sha256'))[:12]}... (corrupted)",
        )
    if expected_sha256 is not None and sha != expected_sha256:
        return False, f"sha256 {sha[:12]}... differs from the lock file's {expected_sha256[:12]}..."
    return True, ""


def read_chunk(directory: Path, i: int) -> dict[str, np.ndarray]:
    with np.load(directory / chunk_name(i), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def remove_chunk(directory: Path, i: int) -> None:
    for name in (chunk_name(i), sidecar_name(i)):
        (directory / name).unlink(missing_ok=True)


def clean_stale_temporaries(directory: Path) -> int:
    """Remove temporary files left by processes that no longer run; returns how many."""
    n = 0
    for p in directory.glob("*.tmp-*"):
        try:
            pid = int(p.name.rsplit(".tmp-", 1)[1])
            os.kill(pid, 0)
            continue  # still running: its file
        except (ValueError, ProcessLookupError):
            pass
        except PermissionError:
            continue
        p.unlink(missing_ok=True)
        n += 1
    return n


def content_hash(chunk_sha256s: list[str]) -> str:
    """sha256 over the chunks' sha256 in order: the hash of the whole dataset's content."""
    return hashlib.sha256("\n".join(chunk_sha256s).encode()).hexdigest()
