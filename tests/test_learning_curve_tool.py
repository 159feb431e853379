"""benchmarks/tools/learning_curve.py: per-context values read from the evaluation files' names, the table's cells and
the --versus difference against hand computations, and its command line (--help, --csv round trip)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest


def _evaluation(path: Path, valid: np.ndarray) -> None:
    """A prior_misses.py-like file: one row per sample, ``valid`` shaped (contexts, samples)."""
    n_contexts, n_samples = valid.shape
    pd.DataFrame(
        {"context": np.repeat(np.arange(n_contexts), n_samples), "valid": valid.reshape(-1).astype(bool)}
    ).to_parquet(path)


def test_the_tables_and_the_paired_difference_match_hand_computations(tmp_path, capsys, bench_tool):
    rng = np.random.default_rng(3)
    early = rng.uniform(size=(20, 10)) < 0.2
    late = rng.uniform(size=(20, 10)) < 0.4
    early[5] = False  # a context without a valid sample: not a success
    _evaluation(tmp_path / "run-1000-dprior.parquet", early)
    _evaluation(tmp_path / "run-2000-dprior.parquet", late)
    _evaluation(tmp_path / "run-2000-mpd-extra.parquet", late)

    tool = bench_tool("learning_curve")
    df = tool.load(sorted(tmp_path.glob("*.parquet")))
    first = df[(df.steps == 1000)].sort_values("context")
    np.testing.assert_allclose(first.valid, early.mean(axis=1))
    np.testing.assert_array_equal(first.success, early.any(axis=1).astype(float))
    assert set(df[df.method == "mpd"].scene) == {"extra objects"}

    tool.main(
        [
            *map(str, sorted(tmp_path.glob("*.parquet"))),
            "--versus",
            "run:2000",
            "run:1000",
            "--csv",
            str(tmp_path / "c.csv"),
        ]
    )
    out = capsys.readouterr().out
    assert f"| run | 1000 | {100 * early.mean():.1f} [" in out
    assert f"/ {100 * early.any(axis=1).mean():.0f} %" in out
    difference = 100 * (late.mean(axis=1) - early.mean(axis=1)).mean()
    assert f"| training | Dprior | {difference:+.1f} [" in out

    # the CSV gives the same tables again
    tool.main([str(tmp_path / "c.csv"), "--versus", "run:2000", "run:1000"])
    assert capsys.readouterr().out == out


def test_a_cvae_training_gives_its_own_columns(tmp_path, capsys, bench_tool):
    """A CVAE's evaluations (``--method cvae`` / ``cvae-cost``) are read as CVAE and CVAE+Cost, not refused or merged
    into Dprior's column."""
    rng = np.random.default_rng(5)
    alone, cost = rng.uniform(size=(8, 10)) < 0.3, rng.uniform(size=(8, 10)) < 0.6
    _evaluation(tmp_path / "cv-5000-cvae.parquet", alone)
    _evaluation(tmp_path / "cv-5000-cvae-cost-extra.parquet", cost)
    tool = bench_tool("learning_curve")
    df = tool.load(sorted(tmp_path.glob("*.parquet")))
    assert set(zip(df.method, df.scene)) == {("cvae", "training"), ("cvae-cost", "extra objects")}
    tool.main([str(p) for p in sorted(tmp_path.glob("*.parquet"))])
    out = capsys.readouterr().out
    (head,) = [line for line in out.splitlines() if line.startswith("| prior |")]
    assert head == "| prior | steps | CVAE, training | CVAE+Cost, extra objects |"  # no MPD - Dprior+Cost column
    assert f"| cv | 5000 | {100 * alone.mean():.1f} [" in out


def test_a_file_named_otherwise_is_refused_by_name(tmp_path, bench_tool):
    bad = tmp_path / "run-dprior.parquet"
    _evaluation(bad, np.ones((2, 2)))
    with pytest.raises(ValueError, match="run-dprior.parquet"):
        bench_tool("learning_curve").load([bad])


def test_help_exits_cleanly_and_no_file_is_an_error(capsys, bench_tool):
    tool = bench_tool("learning_curve")
    with pytest.raises(SystemExit) as done:
        tool.main(["--help"])
    assert done.value.code == 0 and "--versus" in capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        tool.main([])
    assert done.value.code == 2 and "files" in capsys.readouterr().err
