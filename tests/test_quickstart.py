"""docs/QUICKSTART.md, run as written (outside the repository, eager network: MPD_COMPILE=0): it plans with the shipped
Warehouse prior around two new boxes, and writes a figure and a Rerun recording that read back."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "QUICKSTART.md"
BLOCK = re.compile(r"^```(\w+)([^\n]*)\n(.*?)^```", re.S | re.M)


def test_the_quickstart_runs_as_written(tmp_path):
    blocks = BLOCK.findall(DOC.read_text())
    (code,) = [body for lang, info, body in blocks if "file=quickstart.py" in info]
    (console,) = [body for lang, _, body in blocks if lang == "console"]
    assert console.strip() == "$ python quickstart.py"
    (tmp_path / "quickstart.py").write_text(code)
    env = {**os.environ, "MPD_COMPILE": "0", "MPD_CACHE": str(tmp_path / "cache"), "PYTHONPATH": str(REPO)}
    r = subprocess.run([sys.executable, "quickstart.py"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    out = r.stdout
    assert "MotionPlanner(mpd on EnvWarehouse-RobotPanda, model " in out and "goal: pose" in out
    given = float(re.search(r"^valid (\d+)%", out, re.M).group(1))
    blind = float(re.search(r"boxes not given: (\d+)% valid", out).group(1))
    assert given > blind  # the boxes reach the cost: MPD avoids them when told
    assert (tmp_path / "quickstart.png").stat().st_size > 10_000
    from test_recording import STEP, read_back

    entities, times, _ = read_back(tmp_path / "quickstart.rrd")
    assert "/world/samples" in entities or "world/samples" in entities
    assert len(times[STEP]) > 10  # the batch at every denoising step
