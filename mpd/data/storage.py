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


def map_chunk(directory: Path, i: int) -> dict[str, np.ndarray]:
    """The arrays of chunk i memory-mapped (read-only), read from disk only where indexed: a chunk archive is an
    uncompressed zip, so each ``.npy`` member is a contiguous range of the file."""
    path = directory / chunk_name(i)
    out = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as f:
        for info in zf.infolist():
            if info.compress_type != zipfile.ZIP_STORED:  # not written by npz_bytes: read it the ordinary way
                return read_chunk(directory, i)
            f.seek(info.header_offset)
            local = f.read(30)  # the member's local header: its name and extra field lengths at bytes 26-29
            start = (
                info.header_offset
                + 30
                + int.from_bytes(local[26:28], "little")
                + int.from_bytes(local[28:30], "little")
            )
            f.seek(start)
            version = np.lib.format.read_magic(f)
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            shape, fortran, dtype = read_header(f)
            name = info.filename[: -len(".npy")]
            if dtype.hasobject:
                raise ValueError(f"{path}: member {name} holds Python objects")
            if int(np.prod(shape)) == 0:
                out[name] = np.zeros(shape, dtype=dtype)
                continue
            out[name] = np.memmap(
                path, dtype=dtype, mode="r", offset=f.tell(), shape=shape, order="F" if fortran else "C"
            )
    return out


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
