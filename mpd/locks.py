"""One process at a time per artifact of the cache: an exclusive ``fcntl.flock`` on a hidden file beside the
artifact's folder, held while the returned file is open. It is released when the file is closed or garbage-collected,
or when the process dies (a kill -9 leaves no stale lock). A second process of the same artifact waits, then finds it
made. Without ``fcntl`` (Windows) nothing is locked."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


def hold(folder: Path, on_wait: Callable[[], None] | None = None):
    """Lock ``folder`` (which need not exist yet) for this process; ``on_wait`` is called once when another process
    holds it, before waiting. Returns the open lock file: close it (or let it go) to release the lock."""
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    f = open(folder.parent / f".{folder.name}.lock", "a")  # noqa: SIM115 (held open: the lock lives as long as the file)
    try:
        import fcntl
    except ImportError:
        return f
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        if on_wait is not None:
            on_wait()
        fcntl.flock(f, fcntl.LOCK_EX)
    return f
