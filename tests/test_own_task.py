"""A user's own task, kept outside the repository: one identity (its name) whether a spec gives it by name or by
path, and a run of it that writes nothing outside its run folder and the cache."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pandas as pd
import pytest

from mpd.experiments.spec import load_spec
from mpd.schema import ConfigError
from mpd.tasks import load_task, task_files

REPO = Path(__file__).resolve().parents[1]
BASE = "EnvSimple2D-RobotPointMass2D"


def own_task(folder: Path, name: str = "MyTask2D", file: str = "MyTask.toml") -> Path:
    """A copy of a bundled 2-D task under another name, in a folder outside the repository."""
    folder.mkdir(parents=True, exist_ok=True)
    text = task_files()[BASE].read_text()
    assert f'name = "{BASE}"' in text
    p = folder / file
    p.write_text(text.replace(f'name = "{BASE}"', f'name = "{name}"', 1))
    return p


def write_spec(folder: Path, task_entry: str, table_key: str, methods=("gp-cost",), extra: str = "") -> Path:
    p = folder / "spec.toml"
    p.write_text(
        textwrap.dedent(f"""
        name = "own"
        n_contexts = 2
        n_samples = 8
        record_contexts = 1
        [axes]
        task = ["{task_entry}"]
        method = {json.dumps(list(methods))}
        [tasks."{table_key}"]
        dataset = "{folder / "my-data.toml"}"
        """)
        + textwrap.dedent(extra)
    )
    return p


@pytest.mark.parametrize("key", ["name", "path"])
def test_spec_keyed_by_name_or_path_gives_the_name(tmp_path, key):
    task = own_task(tmp_path / "mine")
    spec = load_spec(write_spec(tmp_path, str(task), "MyTask2D" if key == "name" else str(task)))
    assert spec.data.axes["task"] == ["MyTask2D"]
    assert set(spec.data.tasks) == {"MyTask2D"}
    assert spec.task_file("MyTask2D") == task.resolve()
    assert {c.p["task"] for c in spec.cells()} == {"MyTask2D"}
    assert spec.task_name(str(task)) == "MyTask2D"


def test_relative_task_path_is_found_next_to_the_spec(tmp_path, monkeypatch):
    own_task(tmp_path / "mine")
    monkeypatch.chdir(REPO)  # not where the spec is
    spec = load_spec(write_spec(tmp_path, "mine/MyTask.toml", "MyTask2D"))
    assert spec.task_file("MyTask2D") == (tmp_path / "mine" / "MyTask.toml").resolve()


def test_two_files_with_one_name_is_an_error_naming_both(tmp_path):
    a = own_task(tmp_path / "a")
    b = own_task(tmp_path / "b")
    p = write_spec(tmp_path, str(a), "MyTask2D")
    p.write_text(p.read_text().replace(f'task = ["{a}"]', f'task = ["{a}", "{b}"]'))
    with pytest.raises(ConfigError) as e:
        load_spec(p)
    msg = str(e.value)
    assert str(a.resolve()) in msg and str(b.resolve()) in msg and "'MyTask2D'" in msg and "\n" not in msg


def test_a_task_with_two_tables_is_an_error(tmp_path):
    task = own_task(tmp_path / "mine")
    p = write_spec(tmp_path, str(task), "MyTask2D", extra=f'[tasks."{task}"]\ndataset = "x"\n')
    with pytest.raises(ConfigError, match="two tables"):
        load_spec(p)


def test_missing_table_names_both_keys(tmp_path):
    task = own_task(tmp_path / "mine")
    with pytest.raises(ConfigError) as e:
        load_spec(write_spec(tmp_path, str(task), "Other"))
    assert "'MyTask2D'" in str(e.value) and "tasks.MyTask2D" in str(e.value)


def test_a_task_name_must_be_one_file_name_component(tmp_path):
    bad = own_task(tmp_path / "mine", name="my/task")
    with pytest.raises(ConfigError, match="name 'my/task'"):
        load_task(bad)


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def _repo_files() -> dict[Path, int]:
    out = {}
    for p in REPO.rglob("*"):
        rel = p.relative_to(REPO).parts
        if rel[0] in (".git", ".pytest_cache") or "__pycache__" in rel or not p.is_file():
            continue
        out[p] = p.stat().st_mtime_ns
    return out


def test_run_of_an_outside_task_writes_only_its_run_folder_and_the_cache(tmp_path):
    """`mpd run SPEC --report` in a clean environment: HOME, TMPDIR, the working directory, the task's and the
    spec's folder all in tmp_path; afterwards every file in tmp_path is in the run folder or the cache (or is one
    of the inputs), and the repository is unchanged."""
    user = tmp_path / "user"
    task = own_task(user / "tasks")
    (user / "my-data.toml").write_text(
        f'name = "my-data"\ntask = "{task}"\nn_contexts = 48\nseed = 0\nchunk_size = 24\n[checker]\nkind = "spheres"\n'
        "[split]\nval = 0.25\ntest = 0.5\n"
    )
    spec = write_spec(user, str(task), "MyTask2D", methods=("gp-cost", "rrtconnect-cost"))
    inputs = _files(tmp_path)
    for d in ("home", "tmp", "cwd"):
        (tmp_path / d).mkdir()
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
    env.pop("MPLCONFIGDIR", None)
    before = _repo_files()
    r = subprocess.run(
        [sys.executable, "-m", "mpd.cli", "run", str(spec), "--report"],
        cwd=tmp_path / "cwd",
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    (run,) = (tmp_path / "runs").iterdir()
    # every file written is in the run folder or the cache; matplotlib's font cache in $HOME is the library's own
    written = _files(tmp_path) - inputs
    outside = [
        p
        for p in written
        if not p.is_relative_to(run)
        and not p.is_relative_to(tmp_path / "cache")
        and not p.is_relative_to(tmp_path / "home" / ".cache" / "matplotlib")
        and not p.is_relative_to(tmp_path / "home" / ".config" / "matplotlib")
    ]
    assert not outside, outside
    after = _repo_files()
    assert {p for p in after if after[p] != before.get(p)} == set()
    # the task is named by its name everywhere
    summary = (run / "report" / "summary.md").read_text()
    assert "MyTask2D" in summary and str(task) not in summary and str(task.parent) not in summary
    figs = run / "report" / "figures"
    assert all(p.parent == figs for p in figs.rglob("*")), "figure files sit flat in report/figures"
    assert (figs / "trajectories-MyTask2D-train.png").is_file()
    recs = sorted((run / "recordings").iterdir())
    assert recs and all(p.name.startswith("MyTask2D-") and p.suffix == ".rrd" for p in recs)
    df = pd.read_parquet(run / "results.parquet")
    assert set(df["task"]) == {"MyTask2D"}
    assert set(df["task_hash"]) == {load_task(task).file_hash}
    man = json.loads((run / "manifest.json").read_text())
    assert man["task_files"]["MyTask2D"] == {"path": str(task.resolve()), "sha256": load_task(task).file_hash}
    assert f"mpd view {run.name}" in r.stdout
