"""The committed report of a reference `quick` run (``reports/quick/``) is what the code makes from the committed
results table: rebuilding it in a scratch copy gives the same Markdown tables, and every figure it links exists."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from mpd.viz.report import build_report

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "reports" / "quick"
TABLE_FILES = ("summary.md", "paper.md", "timing.md")


def _tables(text: str) -> list[str]:
    return [line.rstrip() for line in text.splitlines() if line.lstrip().startswith("|")]


def test_committed_quick_report_is_complete():
    assert (QUICK / "results.parquet").exists(), "reports/quick/results.parquet is missing"
    assert (QUICK / "manifest.json").exists()
    index = (QUICK / "report" / "index.md").read_text()
    for link in re.findall(r"\]\((figures/[^)]+\.png)\)", index):
        p = QUICK / "report" / link
        assert p.exists() and p.stat().st_size > 1000, f"{link} linked from index.md is missing or empty"
    assert not list(QUICK.rglob("*.rrd")), "recordings are not committed"


def test_committed_quick_report_regenerates_identically(tmp_path):
    run = tmp_path / "quick"
    run.mkdir()
    for name in ("results.parquet", "manifest.json"):
        shutil.copy(QUICK / name, run / name)
    if (QUICK / "histories").exists():
        shutil.copytree(QUICK / "histories", run / "histories")
    index = build_report(run, recordings=False, formats=("png",), dpi=60)
    assert index.exists()
    for name in TABLE_FILES:
        ours = _tables((run / "report" / name).read_text())
        committed = _tables((QUICK / "report" / name).read_text())
        if name != "paper.md":  # the paper states numbers for the Panda tasks only: no rows for EnvSimple2D
            assert ours, f"{name}: no table rebuilt"
        assert ours == committed, f"{name}: the rebuilt tables differ from the committed ones"
    assert (run / "report" / "paper.md").read_text() == (QUICK / "report" / "paper.md").read_text()
    assert _tables(index.read_text()) == _tables((QUICK / "report" / "index.md").read_text())
