"""``mpd report`` (rebuild a run's recordings and report) and ``mpd view`` (open its Rerun recordings)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import quote

import click

WEB_PORT = 9090  # rerun's defaults
GRPC_PORT = 9876


def _resolve(run: str) -> Path:
    from mpd.experiments.runner import resolve_run

    try:
        return resolve_run(run)
    except FileNotFoundError as e:
        raise click.ClickException(str(e)) from None


@click.command("report")
@click.argument("run", default="latest")
@click.option("--no-recordings", is_flag=True, help="do not (re)build the Rerun recordings")
@click.option("--force", is_flag=True, help="rebuild every recording, also those newer than their history")
@click.option(
    "--reference",
    default=None,
    help="the run to compare this one with in reproducibility.md (default: the committed reports/<spec>/)",
)
@click.option("--keep-going", is_flag=True, help="exit 0 even when a figure cannot be drawn (it is listed)")
@click.option("--pdf", is_flag=True, help="write every figure as PDF too (beside its PNG)")
def report(run: str, no_recordings: bool, force: bool, reference: str | None, keep_going: bool, pdf: bool) -> None:
    """Rebuild the recordings and the report of RUN (a run folder, a run id, `latest`, or a spec name: its latest
    run), and print where its index.md is. A figure that cannot be drawn fails the command (exit 1)."""
    from mpd.viz.report import FigureError, build_report

    run_dir = _resolve(run)
    ref = _resolve(reference) if reference else "auto"
    try:
        index = build_report(
            run_dir,
            recordings=not no_recordings,
            force_recordings=force,
            reference=ref,
            keep_going=keep_going,
            formats=("png", "pdf") if pdf else ("png",),
        )
    except FigureError as e:
        raise click.ClickException(f"report {run_dir / 'report' / 'index.md'}: {e} (--keep-going: exit 0)") from None
    recs = sorted((run_dir / "recordings").glob("*.rrd")) if (run_dir / "recordings").exists() else []
    click.echo(f"report: {index}")
    if recs:
        click.echo(f"recordings: {len(recs)} in {run_dir / 'recordings'}  (open them: mpd view {run_dir.name})")


# --------------------------------------------------------------------------------------------------- view
def free_port(preferred: int, host: str = "127.0.0.1") -> int:
    """``preferred`` when nothing listens there, else a port the OS hands out (a viewer of another session may
    hold rerun's default ports)."""
    for port in (preferred, 0):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise click.ClickException("no free TCP port")


def viewer_command(files: list[Path], web: bool, web_port: int, grpc_port: int, bind: str = "127.0.0.1") -> list[str]:
    """The Rerun viewer's command line: native, or a web viewer served on ``bind`` (headless / remote machines)."""
    cmd = [sys.executable, "-m", "rerun_cli"]
    if web:
        cmd += ["--web-viewer", "--bind", bind, "--web-viewer-port", str(web_port), "--port", str(grpc_port)]
    return cmd + [str(f) for f in files]


def viewer_url(web_port: int, grpc_port: int, host: str = "127.0.0.1") -> str:
    """The page that opens the web viewer on this session's data (the viewer page, told where its gRPC proxy is)."""
    return f"http://{host}:{web_port}/?url={quote(f'rerun+http://{host}:{grpc_port}/proxy', safe='')}"


def start_viewer(cmd: list[str], quiet: bool = False) -> subprocess.Popen:
    """Start the viewer in its own process group: ``rerun_cli`` is a Python wrapper around the viewer binary, and
    only a signal to the whole group stops both."""
    out = subprocess.DEVNULL if quiet else None
    return subprocess.Popen(cmd, stdout=out, stderr=out, start_new_session=True)


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # a recycled id owned by someone else: not ours any more
        return False
    return True


def stop_viewer(proc: subprocess.Popen, timeout: float = 5.0) -> None:
    """SIGTERM to the viewer's process group, SIGKILL to what is left after ``timeout``; returns once the wrapper
    is reaped and the group is empty (the viewer binary can outlive the wrapper by a moment)."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            proc.poll()  # reap the wrapper, else it stays a zombie member of the group
            if not _group_alive(proc.pid):
                break
            time.sleep(0.05)
        if not _group_alive(proc.pid):
            break
    proc.wait()


def wait_http(url: str, proc: subprocess.Popen | None = None, timeout: float = 30.0) -> int:
    """The HTTP status of ``url`` once it answers (0 when it did not within ``timeout`` or the process died)."""
    import urllib.error
    import urllib.request

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc is not None and proc.poll() is not None:
            return 0
        try:
            with urllib.request.urlopen(url, timeout=1) as r:
                return r.status
        except urllib.error.HTTPError as e:
            return e.code
        except OSError:
            time.sleep(0.1)
    return 0


@click.command("view")
@click.argument("run", default="latest")
@click.option("--web", is_flag=True, help="serve a web viewer on 127.0.0.1 (headless or remote machines)")
@click.option("--port", type=int, default=WEB_PORT, show_default=True, help="HTTP port of the web viewer")
@click.option("--grpc-port", type=int, default=None, help="port of the viewer's data server (default: 9876 or free)")
@click.option("--only", default=None, help="only recordings whose file name contains this text")
def view(run: str, web: bool, port: int, grpc_port: int | None, only: str | None) -> None:
    """Open the Rerun viewer on the recordings of RUN (built from its histories when missing). Ctrl-C stops it."""
    from mpd.viz.recording import record_run

    run_dir = _resolve(run)
    files = record_run(run_dir)
    if only:
        files = [f for f in files if only in f.name]
    if not files:
        raise click.ClickException(f"{run_dir}: no recordings (the run recorded no context: record_contexts = 0?)")
    grpc = grpc_port or free_port(GRPC_PORT)
    cmd = viewer_command(files, web, port, grpc)
    code = 0
    # the viewer runs in its own session (a terminal's signals do not reach it), so every way out of this process
    # must stop it: Ctrl-C, SIGTERM, SIGHUP (a closed terminal) and exceptions all pass through `finally`
    # SIGINT is set explicitly: a process started in the background of a non-interactive shell (nohup, `cmd &`,
    # CI runners) inherits SIGINT ignored, and Python then leaves it ignored, so Ctrl-C / `kill -INT` did nothing
    previous = {signal.SIGINT: signal.signal(signal.SIGINT, signal.default_int_handler)}
    previous.update({s: signal.signal(s, _raise_signal) for s in STOP_SIGNALS})
    try:
        proc = start_viewer(cmd)
        try:
            if web:
                url = viewer_url(port, grpc)
                if not wait_http(f"http://127.0.0.1:{port}/", proc):
                    raise click.ClickException(f"the web viewer did not start (port {port} in use? try --port)")
                click.echo(f"{len(files)} recording(s) served; open {url}")
                click.echo(f"from another machine: ssh -L {port}:127.0.0.1:{port} -L {grpc}:127.0.0.1:{grpc} <host>")
                click.echo("Ctrl-C stops the viewer.")
            proc.wait()
        except KeyboardInterrupt:
            click.echo("stopping the viewer", err=True)
            code = 128 + signal.SIGINT
        except Signalled as e:
            click.echo(f"stopping the viewer ({signal.Signals(e.signum).name})", err=True)
            code = 128 + e.signum
        finally:
            # a second signal must not cut the clean-up short
            for s in (*STOP_SIGNALS, signal.SIGINT):
                signal.signal(s, signal.SIG_IGN)
            stop_viewer(proc)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    if code:
        sys.exit(code)


STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class Signalled(Exception):
    """SIGTERM or SIGHUP, turned into an exception so that clean-up code runs."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_signal(signum, frame):
    raise Signalled(signum)
