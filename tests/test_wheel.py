"""The installed wheels work outside the repository: `nox -s wheels`'s three wheels (mpd, small; mpd-priors and
mpd-priors-panda, the shipped priors: together every file of mpd/priors, each file in one of them, each wheel under
PyPI's 100 MB limit) installed by name into a fresh virtual environment, then, from an empty folder, the quickstart page
plans with the shipped prior, `mpd plan` finds the shipped prior without --model, and `mpd run quick --dry-run` finds
the built-in spec. The fresh environment takes mpd's dependencies from this one (a path entry, so none of this
environment's mpd: its editable install is a .pth hook that a path entry does not run); `MPD_WHEEL_FULL_INSTALL=1`
installs them from the package index instead (minutes), with the priors through mpd's `priors` extra."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _run(cmd, **kw):
    r = subprocess.run(cmd, capture_output=True, text=True, **kw)
    assert r.returncode == 0, f"{cmd}: {r.stdout[-1500:]}\n{r.stderr[-3000:]}"
    return r.stdout


def test_wheels_install_by_name_and_plan_outside_the_repository(tmp_path):
    dist = tmp_path / "dist"
    priors = {"mpd_priors": "mpd-priors", "mpd_priors_panda": "mpd-priors-panda"}
    for src in (REPO, *(REPO / "packaging" / name for name in priors.values())):
        _run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation", "-w", str(dist)])
    wheels = {w.name.split("-")[0]: w for w in dist.glob("*.whl")}
    assert set(wheels) == {"mpd", *priors}
    assert wheels["mpd"].stat().st_size < 5e6 and all(wheels[p].stat().st_size < 100e6 for p in priors)
    # every shipped file in exactly one priors wheel (the README in both), the Panda tasks' in mpd-priors-panda
    held = {}
    for package in priors:
        for name in zipfile.ZipFile(wheels[package]).namelist():
            if name.startswith(f"{package}/") and not name.endswith((".py", "README.md")):
                held.setdefault(name.split("/", 1)[1], []).append(package)
    source = REPO / "mpd" / "priors"
    shipped = {
        str(f.relative_to(source))
        for f in [*source.glob("models/*/*"), *source.glob("*/dataset-*")]
        if f.suffix in (".pt", ".json", ".npz")
    }
    assert set(held) == shipped and all(len(where) == 1 for where in held.values())
    assert {k for k, (w,) in held.items() if w == "mpd_priors_panda"} == {k for k in shipped if "-RobotPanda/" in k}
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", str(venv)])
    py, mpd_cli = venv / "bin" / "python", venv / "bin" / "mpd"
    if os.environ.get("MPD_WHEEL_FULL_INSTALL") == "1":
        _run([str(py), "-m", "pip", "install", "-q", "--find-links", str(dist), "mpd[priors]"])
    else:
        import sysconfig

        pip = [str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--find-links", str(dist)]
        _run([*pip, "mpd", *priors.values()])  # first: pip would take this environment's mpd for an installed one
        site = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).strip())
        (site / "deps-of-the-test-environment.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    work = tmp_path / "empty folder é"  # outside the repository; a space and a non-ASCII character in the path
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("MPD_CACHE", "PYTHONPATH", "MPD_PRIORS", "MPD_RUNS")}
    env.update(HOME=str(tmp_path / "home"), MPD_COMPILE="0")
    code = re.search(r"```python file=quickstart.py\n(.*?)^```", (REPO / "docs/QUICKSTART.md").read_text(), re.S | re.M)
    (work / "quickstart.py").write_text(code.group(1))
    out = _run([str(py), "quickstart.py"], cwd=work, env=env)
    assert "MotionPlanner(mpd on EnvWarehouse-RobotPanda, model" in out and (work / "quickstart.rrd").is_file()
    where = _run(
        [str(py), "-c", "import mpd, mpd.paths as p; print(mpd.__file__, p.cache_dir(), p.IN_CHECKOUT)"],
        cwd=work,
        env=env,
    )
    assert str(REPO) not in where and "False" in where and str(tmp_path / "home" / ".cache" / "mpd") in where
    out = _run([str(mpd_cli), "plan", "--task", "EnvSimple2D-RobotPointMass2D", "--planner", "mpd", "--n-samples", "8",
                "--start", "-0.8,-0.8", "--goal", "0.8,0.8", "--out", "plan"], cwd=work, env=env)  # fmt: skip
    assert "context 0: success" in out and (work / "plan" / "metrics.json").is_file()
    out = _run([str(mpd_cli), "run", "quick", "--dry-run"], cwd=work, env=env)
    assert "quick" in out
    assert "9565f76e" in _run([str(mpd_cli), "models", "shipped"], cwd=work, env=env)
