"""docs/RESULTS.md is what `mpd report paper` makes from the committed reports, and its verdicts say what the
intervals say."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from mpd import stats
from mpd.viz.report_tables import paper_numbers
from mpd.viz.results_page import ORDERINGS, glance, number_verdict, ordering_verdict, results_page, with_glance

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "RESULTS.md"


def test_committed_results_page_is_what_the_reports_give():
    assert RESULTS.read_text() == results_page(ROOT / "reports"), (
        "docs/RESULTS.md disagrees with the committed reports: regenerate it with `mpd report paper`"
    )


def test_readme_results_at_a_glance_are_what_the_reports_give():
    readme = (ROOT / "README.md").read_text()
    assert with_glance(readme, glance(ROOT / "reports")) == readme, (
        "README.md's results at a glance disagree with the committed reports: regenerate them with `mpd report paper`"
    )


def test_every_number_of_the_paper_has_a_row():
    rows = [line for line in RESULTS.read_text().splitlines() if line.startswith("| Env")]
    numbers = [r for r in rows if r.count("|") == 10]
    assert len(numbers) >= len(paper_numbers())


@pytest.mark.parametrize(
    ("metric", "paper", "lo", "hi", "verdict"),
    [
        ("success", 97.0, 90.0, 99.0, "inside"),
        ("success", 97.0, 97.0, 99.0, "inside"),
        ("vendi", 60.3, 43.1, 58.8, "outside (ours lower)"),
        ("ee_pos_error", 5.2, 9.9, 11.5, "outside (ours higher)"),
        ("time_total", 0.56, 0.5, 0.6, "not comparable: a time depends on the hardware"),
        ("vendi", 3.0, math.nan, math.nan, "not comparable: too few contexts"),
    ],
)
def test_number_verdicts(metric, paper, lo, hi, verdict):
    assert number_verdict(metric, paper, lo, hi).startswith(verdict)


@pytest.mark.parametrize(
    ("lo", "hi", "higher", "verdict"),
    [
        (1.0, 3.0, True, "holds"),
        (-3.0, -1.0, True, "reversed"),
        (-3.0, -1.0, False, "holds"),
        (1.0, 3.0, False, "reversed"),
        (-1.0, 3.0, True, "not resolved"),
        (-1.0, 3.0, False, "not resolved"),
    ],
)
def test_ordering_verdicts(lo, hi, higher, verdict):
    assert ordering_verdict(stats.Estimate((lo + hi) / 2, lo, hi, 10), higher).startswith(verdict)


def test_orderings_cite_the_sentence_of_their_methods():
    """An ordering's reference is a number of the same task, scene and metric, stated for one of its methods."""
    nums = paper_numbers()
    for o in ORDERINGS:
        if o.ref is None:
            continue
        n = nums[o.ref]
        assert (n["task"], n["scene"]) == (o.task, o.scene) and n["method"] in (o.a, o.b), o
        assert n["metric"] == o.metric or (o.metric.startswith("ee_") and n["metric"].startswith("ee_")), o


def test_check_option_fails_on_a_stale_page(tmp_path):
    from click.testing import CliRunner

    from mpd.cli.reports import report

    def mpd_report_paper(out: Path, *extra: str) -> int:
        return CliRunner().invoke(report, ["paper", "--no-readme", "--out", str(out), *extra]).exit_code

    page = tmp_path / "RESULTS.md"
    # the command line as a user runs it (one process of its own); then the same command in this one
    cmd = [sys.executable, "-m", "mpd.cli", "report", "paper", "--no-readme", "--out", str(page), "--check"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 1 and "differs from what the committed reports give" in done.stderr  # missing
    assert mpd_report_paper(page) == 0 and page.read_text() == RESULTS.read_text()
    assert mpd_report_paper(page, "--check") == 0
    page.write_text(page.read_text().replace("| inside |", "| outside (ours higher) |", 1))
    assert mpd_report_paper(page, "--check") == 1


def test_a_rows_source_names_the_models_its_report_trained_otherwise(tmp_path):
    """The "ours from" column names a task's profile and each model the report's spec overrides, with its steps."""
    import json

    from mpd.viz.results_page import _source

    task = "EnvSimple2D-RobotPointMass2D"
    spec = {
        "tasks": {
            task: {
                "profile": "cpu",
                "models": {"diffusion-bspline": {"profile": "paper-decay", "train_steps": 170000}},
            },
            "Other": {"profile": "gpu"},
        }
    }
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "manifest.json").write_text(json.dumps({"spec": spec}))
    assert (
        _source("run", tmp_path, task)
        == "[run](../reports/run/) (`cpu`; diffusion-bspline `paper-decay` 170,000 steps)"
    )
    assert _source("run", tmp_path, "Other") == "[run](../reports/run/) (`gpu`)"
    assert _source("run", tmp_path, "Absent") == "[run](../reports/run/) (`cpu`)"
