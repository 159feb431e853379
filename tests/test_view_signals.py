"""``mpd view --web`` stops its viewer on every way out: a real ``mpd view`` process serving a real recording is
sent SIGINT (Ctrl-C), SIGTERM or SIGHUP (a closed terminal); afterwards no process of its session, nor of the
viewer's own session (``start_new_session``), may remain."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mpd.cli.viz import free_port, wait_http

TASK = "EnvSimple2D-RobotPointMass2D"
REPO = Path(__file__).resolve().parents[1]


def _procs() -> dict[int, tuple[int, int, str]]:
    """pid -> (parent pid, session id, state) of every live process (Linux /proc)."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) "
        out[int(d.name)] = (int(fields[1]), int(fields[3]), fields[0])
    return out


def _descendants(pid: int) -> set[int]:
    procs, found, todo = _procs(), set(), [pid]
    while todo:
        p = todo.pop()
        for c, (ppid, _, _) in procs.items():
            if ppid == p and c not in found:
                found.add(c)
                todo.append(c)
    return found


def _alive_in(sessions: set[int]) -> list[int]:
    """Processes (zombies aside: they hold no CPU and wait only for their parent) of these sessions."""
    return [p for p, (_, sid, state) in _procs().items() if sid in sessions and state != "Z"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from test_recording import fake_history

    run = tmp_path_factory.mktemp("view") / "run"
    (run / "histories").mkdir(parents=True)
    (run / "manifest.json").write_text(json.dumps({"run_id": "run", "cells": []}))
    row = {"task": TASK, "method": "mpd", "extra_objects": False, "context_index": 0, "cell_key": "k"}
    np.savez_compressed(run / "histories" / "k-ctx0.npz", **fake_history(TASK, S=2), row_json=np.array(json.dumps(row)))
    return run


def _as_a_background_job() -> None:
    """What a non-interactive shell does to a job it starts in the background (`cmd &`, nohup, CI runners): SIGINT
    ignored. Python keeps an inherited SIG_IGN, so `mpd view` must install its own SIGINT handler (it once did not,
    and Ctrl-C then left its viewer running: the SIGINT case failed only in CI)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
@pytest.mark.parametrize("background", [False, True], ids=["foreground", "background"])
@pytest.mark.parametrize(
    "sig",
    [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
    ids=lambda s: s.name,
)
def test_view_stops_its_viewer_on_signal(run_dir, sig, background, tmp_path):
    web, grpc = free_port(0), free_port(0)
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONDONTWRITEBYTECODE": "1"}
    cmd = [sys.executable, "-m", "mpd.cli", "view", str(run_dir), "--web", "--port", str(web)]
    log = tmp_path / "view.log"  # a file, not a pipe: a leftover viewer would hold a pipe open
    sessions: set[int] = set()
    with open(log, "w") as out:
        proc = subprocess.Popen(
            [*cmd, "--grpc-port", str(grpc)],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # like a terminal's job: its own session, so the test can list what it left
            preexec_fn=_as_a_background_job if background else None,
        )
    try:
        assert wait_http(f"http://127.0.0.1:{web}/", proc, timeout=120) == 200, log.read_text()
        viewer = _descendants(proc.pid)
        procs = _procs()
        sessions = {proc.pid} | {procs[p][1] for p in viewer if p in procs}
        assert len(sessions) == 2, "the viewer runs in a session of its own"
        proc.send_signal(sig)
        proc.wait(timeout=60)
        # `mpd view` returns only once the viewer's group is empty; the last members may still be on their way to init
        deadline = time.monotonic() + 10
        while _alive_in(sessions) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = _alive_in(sessions)
        assert not left, f"left behind after {sig.name}: {left}"
    finally:
        # whatever failed above, never leave this test's processes running (a leaked web viewer spins a core)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        procs = _procs()
        for sid in {procs[p][1] for p in _alive_in(sessions) if p in procs}:
            try:
                os.killpg(sid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    assert proc.returncode == 128 + sig, log.read_text()
    assert "stopping the viewer" in log.read_text()
