"""docs/OWN_TASK.md, run as written: its files are written to a fresh folder outside the repository and its `$`
commands run in order (``mpd`` is this checkout's CLI); then the run's report names the task and the methods,
figures sit flat, recordings are inside the run folder, and the run wrote nothing anywhere else."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "OWN_TASK.md"
BLOCK = re.compile(r"^```(\w+)([^\n]*)\n(.*?)^```", re.S | re.M)


def doc_steps() -> tuple[dict[str, str], list[str]]:
    """(files to write: path -> text, commands in order) of the walkthrough."""
    files, commands = {}, []
    for lang, info, body in BLOCK.findall(DOC.read_text()):
        m = re.search(r"file=(\S+)", info)
        if m:
            files[m.group(1)] = body
        elif lang == "console":
            commands += [line[2:] for line in body.splitlines() if line.startswith("$ ")]
    return files, commands


def test_the_walkthrough_has_files_and_commands():
    files, commands = doc_steps()
    assert {"myplanners/noisy_line.py", "my-spec.toml"} <= set(files)
    assert any(c.startswith("mpd tasks new ") for c in commands)
    assert any(c.startswith("mpd planners check ") for c in commands)
    assert commands[-1].startswith("mpd run ") and "--report" in commands[-1]


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


@pytest.mark.slow
def test_walkthrough_runs_as_written(tmp_path):
    files, commands = doc_steps()
    work = tmp_path / "work"
    work.mkdir()
    for d in ("home", "tmp"):
        (tmp_path / d).mkdir()
    for rel, text in files.items():
        (work / rel).parent.mkdir(parents=True, exist_ok=True)
        (work / rel).write_text(text)
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "PYTHONDONTWRITEBYTECODE": "1",
        "HOME": str(tmp_path / "home"),
        "TMPDIR": str(tmp_path / "tmp"),
        "MPD_CACHE": str(tmp_path / "cache"),
        "MPD_RUNS": str(tmp_path / "runs"),
        "MPLBACKEND": "Agg",
    }
    prelude = [f'mpd() {{ "{sys.executable}" -m mpd.cli "$@"; }}']
    before_run: set[Path] = set()
    for cmd in commands:
        if cmd.startswith("export "):
            prelude.append(cmd)
            continue
        if cmd.startswith("mpd run "):
            before_run = _files(tmp_path)
        script = "\n".join(["set -e", *prelude, cmd])
        r = subprocess.run(["bash", "-c", script], cwd=work, env=env, capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, f"$ {cmd}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
        if cmd.startswith("mpd planners check "):
            assert "passes the conformance checks" in r.stdout
    (run,) = (tmp_path / "runs").iterdir()
    written = _files(tmp_path) - before_run
    outside = [
        p
        for p in written
        if not p.is_relative_to(run)
        and not p.is_relative_to(tmp_path / "cache")
        and not p.is_relative_to(tmp_path / "home" / ".cache" / "matplotlib")
        and not p.is_relative_to(tmp_path / "home" / ".config" / "matplotlib")
    ]
    assert not outside, outside
    summary = (run / "report" / "summary.md").read_text()
    assert "MyTask2D" in summary and str(work) not in summary
    assert "myplanners.noisy_line:NoisyLine" in summary or "Noisy line" in summary
    figs = run / "report" / "figures"
    assert all(p.parent == figs for p in figs.rglob("*"))
    assert (figs / "swarm.png").is_file() and (figs / "denoising-MyTask2D-train.png").is_file()
    recs = sorted((run / "recordings").glob("*.rrd"))
    assert {r.name.split("-")[1] for r in recs} >= {"mpd"} and all(r.name.startswith("MyTask2D-") for r in recs)
    df = pd.read_parquet(run / "results.parquet")
    assert set(df["method"]) == {"mpd", "myplanners.noisy_line:NoisyLine"} and set(df["task"]) == {"MyTask2D"}
    ours = df[df["method"] == "myplanners.noisy_line:NoisyLine"]
    assert (ours["time_total"] > 0).all(), "the user's planner is timed like the built-in ones"
