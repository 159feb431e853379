"""`mpd.executor`: the serial executor, a real pool of spawned processes and a real local Ray give the same results
for the same items; a worker runs the threads asked for, pinned when it starts; progress messages reach the caller;
a work item's error reaches the caller as it was raised, naming the item."""

from __future__ import annotations

import os

import pytest
import torch

from mpd import executor

ITEMS = [(i, 3) for i in range(6)]


def _work(i: int, n: int) -> tuple[float, int, str | None]:
    """A seeded sum, and the threads this worker runs."""
    executor.report(i)
    x = torch.randn(n, 64, generator=torch.Generator().manual_seed(i), dtype=torch.float64)
    return float(x.sum()), torch.get_num_threads(), os.environ.get("OMP_NUM_THREADS")


def _fail_on_3(i: int, n: int) -> int:
    if i == 3:
        raise ValueError(f"item {i} is bad")
    return i


def _results(mode: str, **kw) -> dict:
    return {item: res for item, res in executor.imap(_work, ITEMS, mode=mode, workers=2, **kw)}


def test_serial_and_a_process_pool_give_the_same_results_and_pin_threads():
    before = torch.get_num_threads()
    seen = []
    serial = _results("serial", threads=1, progress=seen.append)
    assert torch.get_num_threads() == before, "the serial executor restores this process's threads"
    assert seen == [i for i, _ in ITEMS]
    assert {r[1] for r in serial.values()} == {1}
    seen.clear()
    pooled = _results("process", threads=1, progress=seen.append)
    assert sorted(seen) == [i for i, _ in ITEMS], "every progress message of the workers reaches the caller"
    assert {k: v[0] for k, v in pooled.items()} == {k: v[0] for k, v in serial.items()}
    assert {v[1:] for v in pooled.values()} == {(1, "1")}
    two = _results("process", threads=2)
    assert {v[1:] for v in two.values()} == {(2, "2")}


def test_a_failing_item_raises_its_error_naming_the_item():
    for mode in ("serial", "process"):
        name = lambda item: f"work item {item[0]}"  # noqa: E731
        with pytest.raises(ValueError, match="item 3 is bad") as e:
            list(executor.imap(_fail_on_3, ITEMS, mode=mode, workers=2, name=name))
        assert "while running work item 3" in e.value.__notes__, mode


def test_an_unknown_mode_is_refused():
    with pytest.raises(ValueError, match="unknown executor mode 'thread'"):
        list(executor.imap(_work, ITEMS, mode="thread"))


@pytest.mark.ray
def test_local_ray_gives_the_serial_results_with_one_thread_per_worker():
    ray = pytest.importorskip("ray")
    import sys

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # a Ray worker cannot import this file
    try:
        on_ray = _results("ray")
        # a task of two CPUs would get two threads from Ray itself: the worker's setup hook keeps one
        wide = executor.imap(_work, ITEMS[:2], mode="ray", ray_options={"num_cpus": 2})
        assert {res[1:] for _, res in wide} == {(1, "1")}
        with pytest.raises(ValueError, match="item 3 is bad") as e:
            list(executor.imap(_fail_on_3, ITEMS, mode="ray", workers=2, name=lambda item: f"work item {item[0]}"))
        assert "while running work item 3" in e.value.__notes__
    finally:
        ray.shutdown()
        ray.cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    serial = _results("serial", threads=1)
    assert {k: v[0] for k, v in on_ray.items()} == {k: v[0] for k, v in serial.items()}
    assert {v[1:] for v in on_ray.values()} == {(1, "1")}, "a Ray worker pins one thread when it starts"


PARENT = """
import sys, time
from mpd import executor
for item, _ in executor.imap(time.sleep, [(600,), (600,)], mode="process", workers=2, progress=print):
    pass
"""


def _alive(pid: int) -> bool:
    """pid is a process that has not exited (a zombie has: its parent has only not collected it yet)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _pool_workers(pid: int) -> list[int]:
    """The spawned pool workers among pid's children (not the resource tracker)."""
    with open(f"/proc/{pid}/task/{pid}/children") as f:
        children = [int(c) for c in f.read().split()]
    out = []
    for c in children:
        try:
            with open(f"/proc/{c}/cmdline", "rb") as f:
                if b"spawn_main" in f.read():
                    out.append(c)
        except FileNotFoundError:
            pass
    return out


@pytest.mark.skipif(not os.path.exists("/proc/self/task"), reason="reads the process tree from Linux's /proc")
def test_pool_workers_exit_when_the_process_that_started_them_is_killed():
    """kill -9 of a process running a pool (an `mpd data generate --workers 2`) leaves no worker behind: each holds
    both ends of its task queue and would wait forever, with its imports' memory (~0.5 GB for a torch worker)."""
    import signal
    import subprocess
    import sys
    import time

    p = subprocess.Popen([sys.executable, "-c", PARENT], env={**os.environ, "PYTHONPATH": os.getcwd()})
    try:
        deadline = time.monotonic() + 120
        while len(workers := [c for c in _pool_workers(p.pid) if _alive(c)]) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(workers) == 2, "the pool did not start"
        time.sleep(1.0)  # killed during their start or after it: a worker that finds its parent gone exits too
        p.send_signal(signal.SIGKILL)
        p.wait()
        deadline = time.monotonic() + 20
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = [w for w in workers if _alive(w)]
        for w in left:
            os.kill(w, signal.SIGKILL)
        assert not left, f"{len(left)} pool worker(s) outlived the process that started them"
    finally:
        p.kill()
