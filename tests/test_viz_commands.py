"""``mpd report`` and ``mpd view``: the report command on a run found by id, the viewer's command line, and one
real web viewer started on localhost, answering HTTP 200, then stopped with its whole process group."""

from __future__ import annotations

import os

import pandas as pd
import pytest
from click.testing import CliRunner

from mpd.cli.viz import free_port, report, start_viewer, stop_viewer, viewer_command, viewer_url, wait_http


def test_viewer_command_and_url(tmp_path):
    files = [tmp_path / "a.rrd", tmp_path / "b.rrd"]
    native = viewer_command(files, web=False, web_port=9090, grpc_port=9876)
    assert native[1:3] == ["-m", "rerun_cli"] and native[-2:] == [str(f) for f in files]
    assert "--web-viewer" not in native
    web = viewer_command(files, web=True, web_port=9191, grpc_port=9877)
    i = web.index("--bind")
    assert web[i + 1] == "127.0.0.1" and "--web-viewer" in web
    assert web[web.index("--web-viewer-port") + 1] == "9191" and web[web.index("--port") + 1] == "9877"
    assert viewer_url(9191, 9877) == "http://127.0.0.1:9191/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9877%2Fproxy"


def test_web_viewer_starts_answers_and_stops(tmp_path):
    from test_recording import fake_history

    from mpd.viz.recording import record_history

    rrd = record_history(
        tmp_path / "a.rrd", "EnvSimple2D-RobotPointMass2D", {}, fake_history("EnvSimple2D-RobotPointMass2D", S=2)
    )
    web, grpc = free_port(0), free_port(0)
    proc = start_viewer(viewer_command([rrd], True, web, grpc), quiet=True)
    try:
        assert wait_http(f"http://127.0.0.1:{web}/", proc, timeout=60) == 200
    finally:
        stop_viewer(proc)
    assert proc.poll() is not None
    with pytest.raises(ProcessLookupError):  # the viewer binary went with the wrapper: the group is gone
        os.killpg(proc.pid, 0)


def test_report_command_by_run_id(tmp_path, monkeypatch):
    from test_report import make_run

    monkeypatch.setenv("MPD_RUNS", str(tmp_path))
    run = make_run(tmp_path, n_ctx=2, histories=False, small=True)
    df = pd.read_parquet(run / "results.parquet")  # the main cells only: this tests the command, not the figures
    df[(df.rotation_deg == 0) & (df.n_samples == 100) & (df.parametrization == "bspline")].to_parquet(
        run / "results.parquet", index=False
    )
    res = CliRunner().invoke(report, [run.name, "--no-recordings"])
    assert res.exit_code == 0, res.output
    assert f"report: {run / 'report' / 'index.md'}" in res.output
    assert (run / "report" / "index.md").exists()
    res = CliRunner().invoke(report, ["no-such-run"])
    assert res.exit_code != 0 and "no run found" in res.output


def test_mpd_report_group_defaults_to_a_run(tmp_path, monkeypatch):
    """`mpd report RUN` (options before or after RUN) is `mpd report run RUN`; `paper` and `index` are pages."""
    from test_report import make_run

    from mpd.cli.reports import report as group

    monkeypatch.setenv("MPD_RUNS", str(tmp_path))
    run = make_run(tmp_path, n_ctx=2, histories=False, small=True)
    df = pd.read_parquet(run / "results.parquet")
    df[(df.rotation_deg == 0) & (df.n_samples == 100) & (df.parametrization == "bspline")].to_parquet(
        run / "results.parquet", index=False
    )
    for args in ([run.name, "--no-recordings"], ["--no-recordings", run.name], ["run", run.name, "--no-recordings"]):
        res = CliRunner().invoke(group, args)
        assert res.exit_code == 0, (args, res.output)
        assert f"report: {run / 'report' / 'index.md'}" in res.output
    assert not list((run / "report" / "figures").glob("*.pdf"))
    res = CliRunner().invoke(group, ["--help"])
    assert res.exit_code == 0 and "paper" in res.output and "index" in res.output
