"""Every entry point with bad input: each case exits != 0 (or raises ConfigError from Python) with one line naming
the input and no traceback, and nothing already computed is lost or corrupted."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tiny import tiny_definition

from mpd.schema import ConfigError

REPO = Path(__file__).resolve().parents[1]
TASK = "EnvSimple2D-RobotPointMass2D"


def _env(root: Path) -> dict:
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS="1", MPD_CACHE=str(root / "cache"), MPD_RUNS=str(root / "runs"), MPD_PRIORS="none")
    return env


def mpd(root: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mpd.cli", *args],
        cwd=REPO,
        env=_env(root),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def assert_one_line_error(r: subprocess.CompletedProcess, names: str) -> None:
    assert r.returncode != 0, (r.args, r.stdout[-500:], r.stderr[-500:])
    assert "Traceback" not in r.stderr, (r.args, r.stderr[-2000:])
    last = r.stderr.strip().splitlines()[-1]
    assert names in last, (r.args, last)


_definition = tiny_definition


# (argv, text the error's last line names); each runs in a fresh subprocess. Cases that once needed a fix are marked.
CLI_CASES = [
    (["nosuchverb"], "nosuchverb"),
    (["tasks", "check", "{garbage}"], "garbage.toml"),
    (["tasks", "check", "{nonascii}"], "é space.toml"),
    (["tasks", "new", ""], "name ''"),
    (["tasks", "show", "NoSuchTask", "--out", "{root}/o.png"], "NoSuchTask"),
    (["data", "generate", "{garbage}"], "garbage.toml"),
    (["data", "generate", "{baddef}"], "n_contexts"),
    (["data", "generate", "nosuchdef"], "nosuchdef"),
    (["data", "info", "nosuchdataset"], "nosuchdataset"),
    (["train", "--task", "NoSuchTask"], "NoSuchTask"),
    (["train", "--task", TASK, "--steps", "-5"], "--steps"),  # needed a fix (traceback)
    (["train", "--task", TASK, "--steps", "abc"], "--steps"),
    (["train", "--task", TASK, "--threads", "0"], "--threads"),  # needed a fix (trained the whole profile)
    (["train", "--task", TASK, "--profile", "nope"], "nope"),
    (["train", "--task", TASK, "--dataset", "nosuch"], "nosuch"),
    (["train", "--task", TASK, "--device", "bogus", "--steps", "2"], "--device"),  # needed a fix (traceback)
    (["train", "--task", TASK, "--model", "gan"], "--model"),
    (["models", "ship", "{root}/nosuch.pt"], "nosuch.pt"),
    (["plan", "--task", TASK, "--planner", "nope", "--out", "{root}/o"], "nope"),
    (
        ["plan", "--task", TASK, "--planner", "gp-cost", "--start", "nan,0", "--goal", "0.5,0.5", "--out", "{root}/o"],
        "nan",
    ),
    (
        ["plan", "--task", TASK, "--planner", "gp-cost", "--start", "1,2,3", "--goal", "0.5,0.5", "--out", "{root}/o"],
        "--start",
    ),
    (
        ["plan", "--task", TASK, "--planner", "gp-cost", "--start", "a,b", "--goal", "0.5,0.5", "--out", "{root}/o"],
        "a,b",
    ),
    (["plan", "--task", TASK, "--planner", "gp-cost", "--n-samples", "0", "--out", "{root}/o"], "--n-samples"),
    (["plan", "--task", TASK, "--planner", "gp-cost", "--n-contexts", "-1", "--out", "{root}/o"], "--n-contexts"),
    (["plan", "--task", TASK, "--planner", "gp-cost", "--set", "nokey", "--out", "{root}/o"], "nokey"),
    (["plan", "--task", TASK, "--planner", "gp-cost", "--set", "bogus_key=1", "--out", "{root}/o"], "bogus_key"),
    (["plan", "--task", TASK, "--planner", "gp-cost", "--device", "bogus", "--out", "{root}/o"], "--device"),  # same
    (["plan", "--task", TASK, "--planner", "dprior", "--model", "{garbage}", "--out", "{root}/o"], "--model"),
    (["planners", "check", "nosuch"], "nosuch"),
    (["run", "nosuchspec"], "nosuchspec"),
    (["run", "{badspec}"], "badspec.toml"),
    (["run", "{garbage}"], "garbage.toml"),
    (["run", "{badspec}", "--workers", "0"], "--workers"),  # IntRange added with the fixes (not seen failing before)
    (["run", "{badspec}", "--scale", "2"], "--scale"),
    (["run", "{badspec}", "--device", "bogus"], "--device"),  # checked by the same --device fix
    (["runs", "show", "nosuchrun"], "nosuchrun"),
    (["runs", "compare", "nosuchrun", "other"], "nosuchrun"),
    (["report", "nosuchrun"], "nosuchrun"),
    (["report", "run", "nosuchrun"], "nosuchrun"),
    (["view", "nosuchrun"], "nosuchrun"),
]


def _bad_files(root: Path) -> dict[str, str]:
    files = {
        "root": str(root),
        "garbage": str(root / "garbage.toml"),
        "baddef": str(root / "baddef.toml"),
        "badspec": str(root / "badspec.toml"),
        "nonascii": str(root / "é space.toml"),
    }
    Path(files["garbage"]).write_text("this is [not toml\n")
    Path(files["baddef"]).write_text(f'name = "x"\ntask = "{TASK}"\nn_contexts = -3\nseed = 0\n')
    Path(files["badspec"]).write_text('name = 3\n[axes]\nmethod = ["nope"]\n')
    Path(files["nonascii"]).write_text('name = "ü x"\n')
    return files


def _mpd_in_process(root: Path, argv: list[str], monkeypatch, capsys) -> subprocess.CompletedProcess:
    """`mpd ARGV` through the command's own entry point (mpd.cli.main) in this process: its exit status and its
    output, as a subprocess would have them (a SystemExit with a message prints it, as the interpreter does). An
    exception main lets through fails the test with its traceback."""
    from mpd.cli import main

    for k, v in _env(root).items():
        if k.startswith("MPD_") or k == "OMP_NUM_THREADS":
            monkeypatch.setenv(k, v)
    monkeypatch.setattr(sys, "argv", ["mpd", *argv])
    capsys.readouterr()
    code: int | str | None = 0
    try:
        main()
    except SystemExit as e:
        code = e.code
    out, err = capsys.readouterr()
    if isinstance(code, str):
        err, code = err + code + "\n", 1
    return subprocess.CompletedProcess(argv, code or 0, out, err)


def test_every_verb_with_bad_options_fails_in_one_line(tmp_path, monkeypatch, capsys):
    """Every case through the command's entry point in this process (a subprocess per case would spend ~1 s each
    importing torch); the next test runs a few of them as real subprocesses."""
    root = tmp_path / "r oot é"  # spaces and non-ASCII in every path
    root.mkdir()
    files = _bad_files(root)
    failures = []
    for argv, names in CLI_CASES:
        with monkeypatch.context() as m:
            r = _mpd_in_process(root, [a.format(**files) for a in argv], m, capsys)
        try:
            assert_one_line_error(r, names)
        except AssertionError as e:
            failures.append(f"{argv}: {e}")
    assert not failures, "\n".join(failures)
    assert not (root / "cache").exists() or not any((root / "cache").rglob("*.pt"))  # nothing trained by a bad call


@pytest.mark.parametrize("i", [0, 1, 9, len(CLI_CASES) - 1])
def test_bad_options_fail_in_one_line_from_the_installed_command(tmp_path, i):
    """A few of the cases as the user meets them: a fresh `python -m mpd.cli` process, its exit status and stderr."""
    root = tmp_path / "r oot é"
    root.mkdir()
    files = _bad_files(root)
    argv, names = CLI_CASES[i]
    assert_one_line_error(mpd(root, *[a.format(**files) for a in argv]), names)


# ---- bad fields of definition, spec and task files, from Python (ConfigError, naming the file) ----

_values = st.one_of(
    st.integers(-(10**6), 10**6), st.floats(allow_nan=False), st.text(max_size=8), st.booleans(), st.just([])
)


def _toml(v) -> str:
    import json

    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if v == v and abs(v) != float("inf") else "nan"
    return json.dumps(v)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    field=st.sampled_from(["n_contexts", "seed", "chunk_size", "task", "name", "nosuchfield"]),
    value=_values,
)
def test_definition_files_with_bad_fields_raise_config_error(tmp_path, field, value):
    from mpd.data.definition import load_definition

    good = {"name": '"tiny"', "task": f'"{TASK}"', "n_contexts": "32", "seed": "0", "chunk_size": "16"}
    good[field] = _toml(value)
    p = tmp_path / "dé f.toml"
    p.write_text("\n".join(f"{k} = {v}" for k, v in good.items()) + '\n[checker]\nkind = "spheres"\n')
    try:
        load_definition(p)
    except ConfigError as e:
        assert str(p) in str(e) or p.name in str(e)
        assert "\n" not in str(e).strip()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    field=st.sampled_from(["n_contexts", "n_samples", "seeds", "record_contexts", "name", "nosuchfield"]),
    value=_values,
)
def test_spec_files_with_bad_fields_raise_config_error(tmp_path, field, value):
    from mpd.experiments.spec import load_spec

    good = {"name": '"s"', "n_contexts": "4", "n_samples": "16", "seeds": "[0]", "record_contexts": "0"}
    good[field] = _toml(value)
    p = tmp_path / "sp é.toml"
    p.write_text(
        "\n".join(f"{k} = {v}" for k, v in good.items())
        + f'\n[axes]\ntask = ["{TASK}"]\nmethod = ["gp-cost"]\nextra_objects = [false]\n'
    )
    try:
        load_spec(p)
    except ConfigError as e:
        assert p.name in str(e)


def test_task_file_with_a_bad_field_raises_config_error(tmp_path):
    from mpd.tasks import load_task

    src = (REPO / "mpd" / "tasks" / "data" / f"{TASK}.toml").read_text()
    for bad in ["nosuchkey = 1\n" + src, src.replace("schema_version", "schema_versio", 1), src[: len(src) // 2]]:
        p = tmp_path / "tâsk x.toml"
        p.write_text(bad)
        with pytest.raises(ConfigError, match="tâsk x.toml"):
            load_task(p)


# ---- corrupted artifacts in the cache ----


_DURATIONS: dict[str, float] = {}


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A tiny dataset and a 20-step model in a cache under a path with spaces and non-ASCII."""
    root = tmp_path_factory.mktemp("made") / "ca che ü"
    root.mkdir()
    d = _definition(root / "tiny.toml")
    r = mpd(root, "data", "generate", str(d), timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    t1 = time.monotonic()
    r = mpd(root, "train", "--task", TASK, "--dataset", str(d), "--steps", "20", "--threads", "1", timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    _DURATIONS["train"] = time.monotonic() - t1  # this machine's pace, for the kill -9 test
    model = Path(r.stdout.strip().splitlines()[-1].split("model: ", 1)[1])
    return root, d, model


def _snapshot(root: Path) -> dict:
    return {p: p.read_bytes() for p in (root / "cache").rglob("*") if p.is_file()}


def test_a_truncated_dataset_chunk_is_reported_and_regenerated_identically(made, tmp_path):
    root0, d, _ = made
    root = tmp_path / "c ü"
    shutil.copytree(root0, root)
    before = _snapshot(root)
    (chunk,) = [p for p in before if p.name == "chunk-00001.npz"]
    with open(chunk, "r+b") as f:
        f.truncate(100)
    r = mpd(root, "data", "info", str(d))
    assert "unusable" in r.stdout + r.stderr and "truncated" in r.stdout + r.stderr
    assert chunk.stat().st_size == 100  # info reports, never deletes
    r = mpd(root, "data", "generate", str(d), timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    after = _snapshot(root)
    for p, b in before.items():
        if p.parent.name.startswith("tiny-") and p.suffix == ".npz":  # a sidecar .json holds wall times
            assert after[p] == b, p  # the regenerated chunk is byte-identical; the others untouched


def test_a_truncated_checkpoint_is_named_and_the_rest_kept(made, tmp_path):
    root0, _, model = made
    root = tmp_path / "m ü"
    shutil.copytree(root0, root)
    bad = root / model.relative_to(root0)
    data = bad.read_bytes()
    before = {p: b for p, b in _snapshot(root).items() if p != bad}
    bad.write_bytes(data[: len(data) // 3])
    r = mpd(root, "plan", "--task", TASK, "--planner", "dprior", "--model", str(bad), "--out", str(root / "o"))
    assert_one_line_error(r, "--model")
    after = _snapshot(root)
    assert all(after[p] == b for p, b in before.items())


def test_a_garbage_json_next_to_a_dataset_is_named(made, tmp_path):
    root0, d, _ = made
    root = tmp_path / "j ü"
    shutil.copytree(root0, root)
    (lock,) = [p for p in (root / "cache").rglob("lock.json") if p.parent.name.startswith("tiny-")]
    lock.write_text("{not json")
    r = mpd(root, "data", "info", str(d))
    assert "Traceback" not in r.stderr, r.stderr[-2000:]


# ---- concurrent use of one cache ----


def _train(root: Path, d: Path, steps: int) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "mpd.cli", "train", "--task", TASK, "--dataset", str(d), "--steps", str(steps),
         "--threads", "1"],
        cwd=REPO, env=_env(root), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def test_two_trainings_of_one_identity_at_once_give_the_model_of_one(made, tmp_path):
    import torch

    root0, d, _ = made
    shared, alone = tmp_path / "shared", tmp_path / "alone"
    shutil.copytree(root0, shared)
    shutil.copytree(root0, alone)
    a, b = _train(shared, d, 23), _train(shared, d, 23)
    outs = [p.communicate(timeout=300) for p in (a, b)]
    assert a.returncode == 0 and b.returncode == 0, [e[-2000:] for _, e in outs]
    assert sum("step/s" in e for _, e in outs) == 1, "trained twice"  # the other waited on the identity's lock
    paths = {o.strip().splitlines()[-1] for o, _ in outs}
    assert len(paths) == 1, paths
    c = _train(alone, d, 23)
    out, err = c.communicate(timeout=300)
    assert c.returncode == 0, err[-2000:]
    shared_model = Path(paths.pop().split("model: ", 1)[1])
    alone_model = Path(out.strip().splitlines()[-1].split("model: ", 1)[1])
    assert shared_model.relative_to(shared) == alone_model.relative_to(alone)
    wa = torch.load(shared_model, map_location="cpu", weights_only=False)
    wb = torch.load(alone_model, map_location="cpu", weights_only=False)
    for key in ("weights", "ema_weights"):
        assert wa[key].keys() == wb[key].keys()
        assert all(torch.equal(wa[key][k], wb[key][k]) for k in wa[key])
    assert not list(shared_model.parent.glob("*.tmp-*"))  # no temporary left behind


# ---- kill -9 at random times, then resume ----


def _files(d: Path) -> frozenset:
    return frozenset((p, p.stat().st_size) for p in d.rglob("*") if p.is_file()) if d.is_dir() else frozenset()


def _start(root: Path, argv: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "mpd.cli", *argv],
        cwd=REPO, env=_env(root), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip


def _kill(p: subprocess.Popen) -> bool:
    """SIGKILL p; False when it had already exited."""
    if p.poll() is not None:
        return False
    p.kill()
    p.wait()
    return True


def _kill_after_progress(root: Path, argv: list[str], watch: Path, rng, at_most: int) -> int:
    """Run argv again and again, each time SIGKILLing it a random 0-0.2 s after it changed a file under `watch`
    (a chunk or its temporary file appeared or grew), until it finishes (or `at_most` kills): every kill lands
    mid-work, whatever the machine's pace. Returns the number of kills."""
    kills = 0
    for _ in range(at_most):
        before = _files(watch)
        p = _start(root, argv)
        while p.poll() is None and _files(watch) == before:
            time.sleep(0.01)
        time.sleep(rng.uniform(0.0, 0.2))
        if not _kill(p):
            break
        kills += 1
    return kills


def _kill_at_random_times(root: Path, argv: list[str], pace: float, rng, kills: int, attempts: int) -> int:
    """Run argv until it has been SIGKILLed `kills` times (at most `attempts` runs), each at a random fraction
    (0.1-0.7) of `pace`, its uninterrupted duration on this machine (a run that writes nothing until its end, a 20-step
    training, starts over each time). A run that finishes before its kill (the machine got quieter than when `pace`
    was measured) gives its own duration as the new pace, and its model is removed, so that the next run starts
    over instead of finding it done. Returns the number of kills."""
    done = 0
    for _ in range(attempts):
        if done >= kills:
            break
        t0 = time.monotonic()
        p = _start(root, argv)
        try:
            p.wait(timeout=rng.uniform(0.1, 0.7) * pace)
        except subprocess.TimeoutExpired:
            if _kill(p):
                done += 1
                continue
        pace = min(pace, time.monotonic() - t0)
        shutil.rmtree(root / "cache" / "models", ignore_errors=True)
    return done


@pytest.mark.slow  # ~1.5 min on a quiet 2-core CPU
def test_kill_9_at_random_times_then_resume_gives_the_uninterrupted_artifacts(made, tmp_path):
    import random

    import torch

    root0, d, model = made  # the uninterrupted dataset and 20-step model
    root = tmp_path / "k ü"
    root.mkdir()
    (root / "tiny.toml").write_text(d.read_text())
    rng = random.Random(0)
    gen = ["data", "generate", str(root / "tiny.toml")]
    kills = _kill_after_progress(root, gen, root / "cache" / "datasets", rng, at_most=16)
    assert kills >= 2, kills  # two chunks, each with its temporary file: at least two kills mid-work
    r = mpd(root, *gen, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    ref = {p.relative_to(root0): p.read_bytes() for p in (root0 / "cache" / "datasets").rglob("*.npz")}
    got = {p.relative_to(root): p.read_bytes() for p in (root / "cache" / "datasets").rglob("*.npz")}
    assert got == ref
    lock = "lock.json"
    (a,) = [p for p in (root0 / "cache").rglob(lock) if p.parent.name.startswith("tiny-")]
    (b,) = [p for p in (root / "cache").rglob(lock) if p.parent.name.startswith("tiny-")]
    la, lb = json.loads(a.read_text()), json.loads(b.read_text())
    assert la["outs"] == lb["outs"] and la["identity"] == lb["identity"]  # the lock's hashes (its timings differ)
    argv = ["train", "--task", TASK, "--dataset", str(root / "tiny.toml"), "--steps", "20", "--threads", "1"]
    kills += _kill_at_random_times(root, argv, _DURATIONS["train"], rng, kills=max(4, 20 - kills), attempts=40)
    assert kills >= 20, kills  # 20 kills at random points in all
    r = mpd(root, *argv, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (m,) = (root / "cache" / "models").rglob("model.pt")
    assert m.relative_to(root) == model.relative_to(root0)
    wa = torch.load(m, map_location="cpu", weights_only=False)
    wb = torch.load(model, map_location="cpu", weights_only=False)
    for key in ("weights", "ema_weights"):
        assert all(torch.equal(wa[key][k], wb[key][k]) for k in wb[key])


def test_a_full_disk_fails_in_one_line_and_keeps_the_dataset(made, tmp_path):
    """A 200 KiB tmpfs as the cache (needs root; skipped otherwise): the dataset fits, the model's checkpoint does
    not."""
    root0, d, _ = made
    root = tmp_path / "full ü"
    root.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(root)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (not root?)")
    try:
        shutil.copytree(root0 / "cache" / "datasets", root / "cache" / "datasets")
        before = _snapshot(root)
        r = mpd(root, "train", "--task", TASK, "--dataset", str(d), "--steps", "20", "--threads", "1", timeout=300)
        assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr[-2000:]
        # one line naming the file that did not fit (the progress bar's last redraw may follow it)
        assert [ln for ln in r.stderr.splitlines() if "error: " in ln and "No space left on device" in ln]
        after = _snapshot(root)
        assert all(after[p] == b for p, b in before.items())
        assert not list((root / "cache").rglob("model.pt")) and not list((root / "cache").rglob("*.tmp-*"))
    finally:
        subprocess.run(["umount", str(root)], check=False)


# ---- a run's damaged artifacts: results table, recorded history, cached contexts, a deleted manifest ----


@pytest.fixture(scope="module")
def ran(made, tmp_path_factory):
    """A finished run of GPprior+Cost (no model) over the tiny dataset's held-out contexts, one context recorded."""
    from mpd.experiments.runner import Runner
    from mpd.experiments.spec import load_spec

    root0, d, _ = made
    root = tmp_path_factory.mktemp("ran") / "r ü"
    shutil.copytree(root0, root)
    spec = root / "s.toml"
    spec.write_text(
        textwrap.dedent(f"""
        name = "s"
        n_contexts = 3
        n_samples = 8
        record_contexts = 1
        [axes]
        task = ["{TASK}"]
        method = ["gp-cost"]
        [tasks."{TASK}"]
        dataset = "{root / "tiny.toml"}"
        """)
    )
    mp = pytest.MonkeyPatch()
    for k, v in _env(root).items():
        if k.startswith("MPD_"):
            mp.setenv(k, v)
    try:
        Runner(load_spec(spec), run_dir=root / "runs" / "s", progress=False).run()
    finally:
        mp.undo()
    return root, root / "runs" / "s"


def test_a_damaged_results_table_is_rebuilt_from_the_parts_or_named(ran, tmp_path, monkeypatch, capsys):
    from mpd.experiments.results import read_results

    root0, run0 = ran
    root = tmp_path / "t ü"
    shutil.copytree(root0, root)
    run = root / "runs" / "s"
    before = read_results(run)
    table = run / "results.parquet"
    table.write_bytes(table.read_bytes()[:200])  # truncated
    with pytest.warns(UserWarning, match="results.parquet: does not read back"):
        after = read_results(run)
    pd_testing = pytest.importorskip("pandas").testing
    pd_testing.assert_frame_equal(after.reset_index(drop=True), before.reset_index(drop=True))
    shutil.rmtree(run / "parts")  # nothing left to rebuild it from: one line naming the table
    with monkeypatch.context() as m:
        r = _mpd_in_process(root, ["report", "run", str(run), "--no-recordings"], m, capsys)
    assert_one_line_error(r, "results.parquet")


def test_a_damaged_history_costs_its_recording_only(ran, tmp_path, monkeypatch, capsys):
    root0, run0 = ran
    root = tmp_path / "h ü"
    shutil.copytree(root0, root)
    run = root / "runs" / "s"
    (hist,) = sorted((run / "histories").glob("*.npz"))
    hist.write_bytes(hist.read_bytes()[:100])
    import re

    with monkeypatch.context() as m, pytest.warns(UserWarning, match=re.escape(hist.name) + ".*does not read back"):
        r = _mpd_in_process(root, ["report", "run", str(run), "--force"], m, capsys)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (run / "report" / "summary.md").stat().st_size > 0


def test_damaged_cached_contexts_are_made_again_identically(ran, tmp_path, monkeypatch):
    from mpd.data.eval_contexts import load_context_file
    from mpd.experiments.results import read_results
    from mpd.experiments.runner import Runner
    from mpd.experiments.spec import load_spec

    root0, run0 = ran
    root = tmp_path / "c ü"
    shutil.copytree(root0, root)
    files = sorted((root / "cache" / "contexts").glob(f"{TASK}-*.npz"))
    assert files
    good = {f: f.read_bytes() for f in files}
    for f in files:
        f.write_bytes(f.read_bytes()[:64])
    for k, v in _env(root).items():
        if k.startswith("MPD_"):
            monkeypatch.setenv(k, v)
    spec = load_spec(root / "s.toml")
    Runner(spec, run_dir=root / "runs" / "again", progress=False).run()
    for f, b in good.items():
        load_context_file(f)  # reads back, its hash verified
        assert f.read_bytes() == b
    cols = ["cell_key", "context_index", "fraction_valid", "success"]
    a, b = read_results(run0)[cols], read_results(root / "runs" / "again")[cols]
    assert a.sort_values(cols[:2]).to_numpy().tolist() == b.sort_values(cols[:2]).to_numpy().tolist()


def test_a_run_folder_losing_its_files_reports_what_is_left_or_fails_in_one_line(ran, tmp_path, monkeypatch, capsys):
    """Files of a run folder deleted (by hand, or by a cleanup while a report runs): without its manifest the report
    is still written from the results; without its results it fails in one line."""
    root0, _ = ran
    root = tmp_path / "m ü"
    shutil.copytree(root0, root)
    run = root / "runs" / "s"
    (run / "manifest.json").unlink()
    with monkeypatch.context() as m:
        r = _mpd_in_process(root, ["report", "run", str(run), "--no-recordings"], m, capsys)
    assert r.returncode == 0 and (run / "report" / "summary.md").is_file(), r.stderr[-2000:]
    (run / "results.parquet").unlink()
    shutil.rmtree(run / "parts")
    for argv, names in (
        (["report", "run", str(run), "--no-recordings"], "results.parquet"),
        (["runs", "show", str(run)], "manifest.json"),
    ):
        with monkeypatch.context() as m:
            r = _mpd_in_process(root, argv, m, capsys)
        assert_one_line_error(r, names)


@pytest.mark.slow  # two runs, each generating and training (~1 min on 2 cores)
def test_two_runs_of_overlapping_specs_on_one_cache_at_once(made, tmp_path):
    """Two `mpd run` of specs that need the same dataset and model, started together on one empty cache: both
    finish, the dataset is the one a single generation writes (byte for byte), one model is trained (the second run
    waits for the first's), and the cells both runs have give the same rows."""
    from mpd.experiments.results import read_results

    root0, d, _ = made
    root = tmp_path / "two ü"
    root.mkdir()
    (root / "tiny.toml").write_text(d.read_text())

    def spec(name: str, methods: str) -> Path:
        p = root / f"{name}.toml"
        p.write_text(
            textwrap.dedent(f"""
            name = "{name}"
            n_contexts = 2
            n_samples = 8
            record_contexts = 0
            [axes]
            task = ["{TASK}"]
            method = [{methods}]
            "training.steps" = [20]
            [tasks."{TASK}"]
            dataset = "{root / "tiny.toml"}"
            """)
        )
        return p

    a, b = spec("a", '"gp-cost", "dprior"'), spec("b", '"dprior"')
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "mpd.cli", "run", str(s), "--run-dir", str(root / "runs" / s.stem)],
            cwd=REPO,
            env=_env(root),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for s in (a, b)
    ]
    for p in procs:
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-2000:]
    ref = {p.relative_to(root0): p.read_bytes() for p in (root0 / "cache" / "datasets").rglob("*.npz")}
    got = {p.relative_to(root): p.read_bytes() for p in (root / "cache" / "datasets").rglob("*.npz")}
    assert got == ref
    assert len(list((root / "cache" / "models").rglob("model.pt"))) == 1
    assert not list((root / "cache").rglob("*.tmp-*"))
    cols = ["context_index", "fraction_valid", "success", "path_length", "model_id"]
    ra, rb = read_results(root / "runs" / "a"), read_results(root / "runs" / "b")
    da = ra[ra["method"] == "dprior"].sort_values("context_index")[cols].reset_index(drop=True)
    db = rb[rb["method"] == "dprior"].sort_values("context_index")[cols].reset_index(drop=True)
    assert len(da) == 2 and da.equals(db)  # NaN (no valid path) equals NaN here


def test_a_held_artifact_lock_makes_another_process_wait_until_it_is_released(tmp_path):
    """mpd.locks.hold: a second process of the same artifact says it waits and goes on only when the first lets go
    (a real flock between two processes, as between two `mpd run` of one dataset)."""
    from mpd import locks

    folder = tmp_path / "ds ü" / "tiny-0123"
    held = locks.hold(folder)
    code = (
        "import sys, time; from pathlib import Path; from mpd import locks; t = time.monotonic(); "
        "f = locks.hold(Path(sys.argv[1]), lambda: print('waiting', flush=True)); "
        "print(f'got {time.monotonic() - t:.2f}', flush=True)"
    )
    p = subprocess.Popen([sys.executable, "-c", code, str(folder)], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "waiting"
    time.sleep(1.0)
    assert p.poll() is None  # still waiting
    held.close()
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 0 and out.startswith("got ") and float(out.split()[1]) >= 1.0
