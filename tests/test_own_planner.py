"""A user's own planner, defined outside the repository: named as ``package.module:Class`` or installed through the
``mpd.planners`` entry point group, it passes the conformance checks the built-in planners pass, runs in a spec
beside them, timed and recorded the same way; a broken one fails the check with one line naming what broke."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pandas as pd
import pytest
from test_walkthrough import doc_steps

from mpd.planners import PLANNERS, get_planner_class
from mpd.planners.conformance import PlannerCheckError, check_planner

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = "myplanners.noisy_line:NoisyLine"


@pytest.fixture
def user_package(tmp_path, monkeypatch):
    """The walkthrough's example package (docs/OWN_TASK.md), in a folder outside the repository, on sys.path."""
    root = tmp_path / "userpkgs"
    files, _ = doc_steps()
    for rel, text in files.items():
        if rel.startswith("myplanners/"):
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_text(text)
    monkeypatch.syspath_prepend(str(root))
    yield root
    for name in [m for m in sys.modules if m == "myplanners" or m.startswith(("myplanners.", "broken"))]:
        del sys.modules[name]


@pytest.mark.parametrize("name", sorted(PLANNERS))
def test_the_built_in_planners_pass_the_checks(name):
    rep = check_planner(name)
    assert rep.planner == name and len(rep.checks) >= 5


def test_the_example_planner_passes_the_checks(user_package):
    cls = get_planner_class(EXAMPLE)
    assert cls.__module__ == "myplanners.noisy_line" and cls.name == "noisy-line"
    assert any(c.startswith("determinism") for c in check_planner(EXAMPLE).checks)


BROKEN = {
    # what breaks -> (class body replacing NoisyLine's plan, the check that must name it)
    "seed": ("noise = torch.randn(n_samples, n_free, self.task.dof)", "determinism"),
    "shape": ("noise = torch.randn(n_samples + 1, n_free, self.task.dof, generator=gen)", "shapes"),
    "timing": ("", "timings"),  # no timer("total") around the work
}


def _broken_module(root: Path, what: str) -> str:
    text = (root / "myplanners" / "noisy_line.py").read_text()
    if what == "timing":  # no timer("total") around the work
        text = text.replace('with timer("total"):', "if True:")
    else:
        line = next(li for li in text.splitlines() if "noise = torch.randn(" in li)
        text = text.replace(line.strip(), BROKEN[what][0])
    name = f"broken_{what}"
    (root / f"{name}.py").write_text(text)
    return f"{name}:NoisyLine"


@pytest.mark.parametrize("what", sorted(BROKEN))
def test_a_broken_planner_fails_the_check_in_one_line(user_package, what):
    ref = _broken_module(user_package, what)
    with pytest.raises(PlannerCheckError) as e:
        check_planner(ref)
    msg = str(e.value)
    assert msg.startswith(f"planner {ref!r}: {BROKEN[what][1]}: ") and "\n" not in msg


@pytest.mark.parametrize(
    ("ref", "expect"),
    [
        ("nosuchmodule_xyz:Planner", "cannot import 'nosuchmodule_xyz'"),
        ("myplanners.noisy_line:Missing", "has no 'Missing'"),
        ("myplanners.noisy_line:torch", "is not a subclass of mpd.planners.Planner"),
        ("no-such-planner", "unknown planner 'no-such-planner'"),
    ],
)
def test_a_planner_that_is_not_one_is_named(user_package, ref, expect):
    with pytest.raises(PlannerCheckError, match=expect):
        check_planner(ref)


def _env(*paths: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), *map(str, paths)]), "PYTHONDONTWRITEBYTECODE": "1"}


def test_the_check_command_exits_1_with_one_line(user_package):
    ref = _broken_module(user_package, "seed")
    cmd = [sys.executable, "-m", "mpd.cli", "planners", "check", ref]
    r = subprocess.run(cmd, capture_output=True, text=True, env=_env(user_package), timeout=300)
    assert r.returncode == 1 and r.stderr.strip().count("\n") == 0 and "determinism" in r.stderr, r.stderr


def test_an_installed_entry_point_is_found_by_its_name(user_package):
    """What `pip install` of a package with ``[project.entry-points."mpd.planners"]`` leaves on sys.path: a
    dist-info folder whose entry_points.txt names the class."""
    info = user_package / "myplanners-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: myplanners\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[mpd.planners]\nnoisy-line = {EXAMPLE}\n")
    env = _env(user_package)
    r = subprocess.run(
        [sys.executable, "-m", "mpd.cli", "planners", "list"], capture_output=True, text=True, env=env, timeout=300
    )
    assert r.returncode == 0 and "noisy-line" in r.stdout and "Noisy line" in r.stdout, r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "mpd.cli", "planners", "check", "noisy-line"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert r.returncode == 0 and "passes the conformance checks" in r.stdout, r.stderr


def test_the_user_planner_runs_in_a_spec_beside_a_built_in_one(user_package, tmp_path, monkeypatch):
    from test_own_task import own_task

    from mpd.experiments.results import read_results
    from mpd.experiments.runner import Runner
    from mpd.experiments.spec import load_spec

    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MPD_RUNS", str(tmp_path / "runs"))
    task = own_task(tmp_path / "mine")
    (tmp_path / "my-data.toml").write_text(
        f'name = "my-data"\ntask = "{task}"\nn_contexts = 48\nseed = 0\nchunk_size = 24\n[checker]\nkind = "spheres"\n'
        "[split]\nval = 0.25\ntest = 0.5\n"
    )
    spec = tmp_path / "spec.toml"
    spec.write_text(
        textwrap.dedent(f"""
        name = "mine"
        n_contexts = 2
        n_samples = 8
        record_contexts = 1
        [axes]
        task = ["{task}"]
        method = ["gp-cost", "{EXAMPLE}"]
        [tasks."MyTask2D"]
        dataset = "my-data.toml"
        """)
    )
    from mpd.viz.recording import stream_unit

    run = Runner(load_spec(spec), progress=False, recorder=stream_unit).run()  # the recorder `mpd run` streams with
    df = read_results(run)
    assert set(df["method"]) == {"gp-cost", EXAMPLE} and len(df) == 4
    ours = df[df["method"] == EXAMPLE]
    assert (ours["time_total"] > 0).all() and ours["success"].notna().all() and ours["task_hash"].notna().all()
    recs = sorted(p.name for p in (run / "recordings").glob("*.rrd"))
    assert "MyTask2D-myplanners.noisy_line_NoisyLine-train-ctx0.rrd" in recs
    assert isinstance(pd.read_parquet(run / "results.parquet"), pd.DataFrame)
