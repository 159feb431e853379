"""Work items mapped onto an executor: this process, a pool of spawned processes, or Ray tasks.

Every stage that runs work side by side (dataset chunks, trainings, planning units) calls `imap`, which yields each
item's result as soon as it is finished, so a caller writes its chunks or rows as they arrive.

Threads are pinned where a worker starts and nowhere else: a pool worker's initializer, a Ray worker's setup hook
(installed by `mpd.distributed.init`), each setting ``OMP_NUM_THREADS`` (read by what the worker imports or starts
later) and torch's intra-op threads. Two workers of two threads each on two cores run many times slower. The
serial executor sets this process's threads for its run and restores them after.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any

MODES = ("serial", "process", "ray")
RAY_OPTIONS = {"num_cpus": 1, "max_retries": 3}  # max_retries: Ray reruns an item whose worker died (not an error)
_POLL_S = 0.2  # how often progress messages are passed on while the pool works
_PARENT_POLL_S = 1.0  # how often a pool worker looks whether the process that started it is still there

_REPORT: Callable[[Any], None] | None = None  # where `report` sends a message, in this process


def report(message: Any) -> None:
    """Called by a work item: passes ``message`` to the ``progress`` of `imap` (a no-op in a Ray task)."""
    if _REPORT is not None:
        _REPORT(message)


def pin_threads(threads: int = 1) -> None:
    """A worker's thread settings, once, when it starts (the pool's initializer; Ray's setup hook, one thread)."""
    os.environ["OMP_NUM_THREADS"] = str(threads)
    import torch

    torch.set_num_threads(threads)


@contextmanager
def threads(n: int | None):
    """torch's intra-op threads of this process set to ``n`` (None: left as they are) for a while."""
    import torch

    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _exit_with(parent: int) -> None:
    """Ends this worker when the process that started it is gone (a ``kill -9`` of ``mpd``): a pool worker holds
    both ends of its task queue, so it would otherwise wait for work forever, with the memory of its imports."""
    import threading
    import time

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(_PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="mpd-parent-watch", daemon=True).start()


def _init_worker(n: int | None, messages, parent: int | None = None) -> None:
    global _REPORT
    if parent is not None:
        _exit_with(parent)
    if n:
        pin_threads(n)
    if messages is not None:
        _REPORT = messages.put


def imap(
    fn: Callable,
    items: Iterable[tuple],
    mode: str = "serial",
    workers: int = 1,
    threads: int | None = 1,
    progress: Callable[[Any], None] | None = None,
    ray_options: dict | None = None,
    address: str | None = None,
    name: Callable[[tuple], str] = repr,
) -> Iterator[tuple[tuple, Any]]:
    """``(item, fn(*item))`` for every item (a tuple of ``fn``'s arguments), in the order they finish.

    Args:
        mode: "serial" (this process, in order), "process" (``workers`` spawned processes; at most two items per
            worker are queued at a time) or "ray" (every item a Ray task of ``ray_options``, by default one CPU and
            three retries, on the cluster at ``address`` or a local Ray of ``workers`` CPUs; one thread each).
        threads: torch threads of each worker (None: the pool's default; serial: this process's as they are).
        progress: called in this process with every message a work item passes to `report` (serial, process).
        name: names an item in the note added to its error (the error itself is re-raised as the item raised it).
    """
    if mode not in MODES:
        raise ValueError(f"unknown executor mode {mode!r} ({', '.join(MODES)})")
    if mode == "serial":
        return _serial(fn, iter(items), threads, progress, name)
    if mode == "process":
        return _pool(fn, iter(items), workers, threads, progress, name)
    return _ray(fn, iter(items), workers, ray_options, address, name)


def _name(e: BaseException, item: tuple, name) -> None:
    e.add_note(f"while running {name(item)}")


def _serial(fn, items: Iterator[tuple], n: int | None, progress, name) -> Iterator[tuple[tuple, Any]]:
    global _REPORT
    before, _REPORT = _REPORT, progress
    try:
        with threads(n):
            for item in items:
                try:
                    result = fn(*item)
                except Exception as e:
                    _name(e, item, name)
                    raise
                yield item, result
    finally:
        _REPORT = before


def _pool(fn, items: Iterator[tuple], workers: int, n: int | None, progress, name) -> Iterator[tuple[tuple, Any]]:
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")  # no fork: torch's thread pools and PyBullet do not survive it
    # written straight to the pipe (no feeder thread): an item's messages are there before its result
    messages = ctx.SimpleQueue() if progress is not None else None

    def drain() -> None:
        while messages is not None and not messages.empty():
            progress(messages.get())

    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker, initargs=(n, messages, os.getpid()))
    try:
        pending = {}
        for item in items:
            pending[pool.submit(fn, *item)] = item
            if len(pending) >= 2 * workers:
                break
        while pending:
            finished, _ = wait(pending, timeout=_POLL_S, return_when=FIRST_COMPLETED)
            drain()
            for f in finished:
                item = pending.pop(f)
                try:
                    result = f.result()  # a worker's error, with its traceback as the cause
                except Exception as e:
                    _name(e, item, name)
                    raise
                nxt = next(items, None)
                if nxt is not None:
                    pending[pool.submit(fn, *nxt)] = nxt
                yield item, result
        drain()
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def _ray(fn, items: Iterator[tuple], workers: int, options, address: str | None, name) -> Iterator[tuple[tuple, Any]]:
    import ray

    from mpd import distributed

    distributed.init(address, workers)  # (already connected: as it is)
    remote = ray.remote(**{**RAY_OPTIONS, **(options or {})})(fn)
    refs = {remote.remote(*item): item for item in items}
    while refs:
        ready, _ = ray.wait(list(refs), num_returns=1)
        for ref in ready:
            item = refs.pop(ref)
            try:
                result = ray.get(ref)
            except Exception as e:
                _name(e, item, name)
                raise
            yield item, result


__all__ = ["MODES", "RAY_OPTIONS", "imap", "pin_threads", "report", "threads"]
