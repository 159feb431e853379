"""A report that cannot draw a figure fails (one line naming the figure and the reason) unless asked to keep going,
and the swarm figure's success bars on tables like the one that broke it: few contexts, a method that never
succeeds, another that always does, NaN diversity."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from mpd.stats import wilson
from mpd.viz import report_figures as rf
from mpd.viz.report import FigureError, build_report
from mpd.viz.report_data import prepare

SIMPLE = "EnvSimple2D-RobotPointMass2D"


@pytest.mark.parametrize("n", range(1, 31))
def test_success_error_bars_are_never_negative(n):
    for k in (0, n // 2, n):
        mean = k / n
        lo, hi = wilson(k, n)
        (below,), (above,) = rf.success_yerr(mean, lo, hi)
        assert below >= 0 and above >= 0
        # against the interval itself: the bar spans [lo, hi] (clipped at the rate, where rounding crossed it)
        assert below == pytest.approx(max(100 * (mean - lo), 0.0), abs=1e-9)
        assert above == pytest.approx(max(100 * (hi - mean), 0.0), abs=1e-9)
        if k == 0:
            assert below == pytest.approx(0.0, abs=1e-9)
        if k == n:
            assert above == pytest.approx(0.0, abs=1e-9)
    assert rf.success_yerr(np.nan, *wilson(0, 0)) == [[0.0], [0.0]]


@pytest.mark.parametrize("n_ctx", [6, 11, 21])  # sizes where the Wilson bound of 0 or 1 rounds past the rate
def test_swarm_figure_with_all_and_no_successes_and_nan_vendi(n_ctx):
    from test_report import _rows

    rng = np.random.default_rng(0)
    rows = []
    for extra in (False, True):
        rows += _rows(rng, SIMPLE, "mpd", n_ctx, extra=extra)
        rows += _rows(rng, SIMPLE, "gp-cost", n_ctx, extra=extra)
    df = pd.DataFrame(rows)
    df.loc[df.method == "mpd", "success"] = 1.0
    gp = df.method == "gp-cost"
    # gp-cost: some successes in the training scene, none with the extra objects
    df.loc[gp, "success"] = ((df.context_index % 3 == 0) & ~df.extra_objects)[gp].astype(float)
    df.loc[gp, "vendi"] = np.nan
    df.loc[gp, "fraction_valid"] = 0.0
    fig = rf.swarm_figure(prepare(df))
    assert fig is not None
    for ax in fig.axes:
        for coll in ax.collections:  # the error bars (LineCollections): every segment upright and finite
            for seg in getattr(coll, "get_segments", lambda: [])():
                seg = np.asarray(seg)
                if len(seg) == 2 and seg[0, 0] == seg[1, 0]:
                    assert np.isfinite(seg).all() and seg[1, 1] >= seg[0, 1]


def _run_with_unloadable_task(tmp_path):
    """A run whose recorded history names a task this checkout does not have: its figures cannot be drawn."""
    from test_report import make_run

    run = make_run(tmp_path, n_ctx=2, histories=True, small=True)
    df = pd.read_parquet(run / "results.parquet")
    df[(df.rotation_deg == 0) & (df.n_samples == 100) & (df.parametrization == "bspline")].to_parquet(
        run / "results.parquet", index=False
    )
    (h,) = (run / "histories").glob("*.npz")
    with np.load(h) as z:
        arrays = {k: z[k] for k in z.files}
    row = json.loads(str(arrays.pop("row_json")))
    row["task"] = "EnvGone-RobotPointMass2D"
    np.savez_compressed(h, **arrays, row_json=np.array(json.dumps(row)))
    return run


def test_report_fails_naming_the_figure_unless_keep_going(tmp_path):
    run = _run_with_unloadable_task(tmp_path)
    with pytest.raises(FigureError) as e:
        build_report(run, recordings=False, formats=("png",), dpi=50)
    msg = str(e.value)
    assert "denoising-EnvGone-RobotPointMass2D-train" in msg and "task not loadable" in msg and "\n" not in msg
    index = build_report(run, recordings=False, formats=("png",), dpi=50, keep_going=True)
    text = index.read_text()
    assert "Not produced" in text and "task not loadable" in text


def test_report_command_exits_non_zero_with_one_line(tmp_path, monkeypatch):
    from mpd.cli.viz import report

    monkeypatch.setenv("MPD_RUNS", str(tmp_path))
    run = _run_with_unloadable_task(tmp_path)
    res = CliRunner().invoke(report, [str(run), "--no-recordings"])
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "denoising-EnvGone-RobotPointMass2D-train" in lines[0], res.output
    res = CliRunner().invoke(report, [str(run), "--no-recordings", "--keep-going"])
    assert res.exit_code == 0, res.output
