"""Experiment specs, the runner (resume after kill -9, determinism, Ray vs local), provenance and run tracking.

Runs here use GPprior+Cost (no model to train) on EnvSimple2D with a tiny dataset, in a private cache.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest
from tiny import write_spec_file

from mpd.experiments.results import RowStore, read_results
from mpd.experiments.runner import Runner
from mpd.experiments.spec import SPEC_DIR, load_spec
from mpd.schema import ConfigError

TASK = "EnvSimple2D-RobotPointMass2D"
METRIC_COLUMNS = ["success", "fraction_valid", "vendi", "path_length", "smoothness", "best_index"]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A private cache and runs folder, and a tiny dataset definition."""
    root = tmp_path_factory.mktemp("experiments")
    old = {k: os.environ.get(k) for k in ("MPD_CACHE", "MPD_RUNS")}
    os.environ["MPD_CACHE"] = str(root / "cache")
    os.environ["MPD_RUNS"] = str(root / "runs")
    for seed in (0, 1):
        (root / f"tiny{seed}.toml").write_text(
            textwrap.dedent(f"""
            name = "tiny{seed}"
            task = "{TASK}"
            n_contexts = 64
            seed = {seed}
            chunk_size = 32
            [checker]
            kind = "spheres"
            [split]
            val = 0.3
            test = 0.5
            """)
        )
    yield root
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def write_spec(
    root: Path,
    name: str,
    body: str = "",
    dataset: str = "tiny0",
    n_contexts: int = 4,
    axes: dict | None = None,
) -> Path:
    """A spec of gp-cost in both scenes on the tiny dataset (``axes``: other axes than method and scene; ``body``:
    TOML text after them)."""
    axes = {"method": ["gp-cost"], "extra_objects": [False, True]} if axes is None else axes
    return write_spec_file(
        root / f"{name}.toml",
        axes={"task": [TASK], **axes},
        after_axes=body,
        tasks={TASK: {"dataset": f"{root / dataset}.toml"}},
        name=name,
        n_contexts=n_contexts,
        n_samples=16,
        seeds=[0],
        record_contexts=0,
    )


# ---------------------------------------------------------------------------------------------------- specs
@pytest.mark.parametrize(
    ("edit", "where"),
    [
        ("n_context = 3\n", "n_context"),
        ('[axes]\nmethod = ["gp-cost", "nope"]\n', "axes.method"),
        ('[axes]\ntask = ["EnvNope"]\n', "axes.task"),
        ('[axes]\npreset = ["offical"]\n', "axes.preset"),
        ('[axes]\nparametrization = ["waypoints"]\n', "axes"),
        ("[axes]\nwidth = [1]\n", "axes.width"),
        ('[axes]\n"planner.guide_rate" = [1.0]\n', "axes.planner.guide_rate"),
        ("[axes]\nn_samples = [0]\n", "axes.n_samples"),
        ('[task]\ncontexts = "sampled"\nturn_contexts = true\n', f"tasks.{TASK}.turn_contexts"),
        ('[task]\nmodels.diffusion-splines = { profile = "paper" }\n', f"tasks.{TASK}.models.diffusion-splines"),
        ('[task]\nmodels.diffusion-bspline = { profile = "nope" }\n', f"tasks.{TASK}.models.diffusion-bspline.profile"),
        ("[task]\nmodels.cvae = { train_steps = 0 }\n", f"tasks.{TASK}.models.cvae.train_steps"),
        ("[task]\nmodels.cvae = {}\n", f"tasks.{TASK}.models.cvae"),
    ],
)
def test_spec_errors_name_file_and_key(tmp_path, edit, where):
    base = {
        "name": '"bad"',
        "n_samples": "4",
    }
    axes = {"task": f'["{TASK}"]', "method": '["gp-cost"]'}
    top = dict(base)
    task_lines = ""
    if edit.startswith("[task]"):  # lines of the task's table
        task_lines = edit[len("[task]\n") :]
    elif edit.startswith("[axes]"):
        for line in edit.splitlines()[1:]:
            k, v = line.split(" = ")
            axes[k] = v
    else:
        k, v = edit.strip().split(" = ")
        top[k] = v
    text = "\n".join(f"{k} = {v}" for k, v in top.items()) + "\n[axes]\n"
    text += "\n".join(f"{k} = {v}" for k, v in axes.items())
    text += f'\n[tasks."{TASK}"]\ndataset = "x"\n' + task_lines
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_spec(p)
    msg = str(e.value)
    assert str(p) in msg and where in msg and "\n" not in msg


def test_cli_reports_one_line_and_exit_code_2(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text(f'name = "bad"\n[axes]\ntask = ["{TASK}"]\nmethod = ["mdp"]\n[tasks."{TASK}"]\ndataset = "x"\n')
    r = subprocess.run([sys.executable, "-m", "mpd.cli", "run", str(p), "--dry-run"], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "axes.method" in r.stderr and "'mdp'" in r.stderr


def test_matrix_expansion_exclude_only_and_collapse(tmp_path):
    p = write_spec(
        tmp_path,
        "m",
        """
        [[exclude]]
        method = "mpd"
        rotation_deg = 30
        """,
        axes={
            "method": ["gp-cost", "mpd"],
            "extra_objects": [False, True],
            "sampler": ["ddim", "ddpm"],
            "rotation_deg": [0, 30],
        },
    )
    spec = load_spec(p)
    cells = spec.cells()
    # gp-cost: sampler collapsed -> 2 scenes x 2 rotations; mpd: 2 samplers x 2 scenes x rotation 0
    assert len([c for c in cells if c.p["method"] == "gp-cost"]) == 4
    assert all(c.p["sampler"] is None for c in cells if c.p["method"] == "gp-cost")
    assert len([c for c in cells if c.p["method"] == "mpd"]) == 4
    assert not any(c.p["method"] == "mpd" and c.p["rotation_deg"] == 30 for c in cells)
    only = spec.cells({"method": ["mpd"], "sampler": ["ddpm"]})
    assert len(only) == 2 and {c.p["extra_objects"] for c in only} == {False, True}
    assert len({c.key for c in cells}) == len(cells)


@pytest.mark.parametrize("name", sorted(p.stem for p in SPEC_DIR.glob("*.toml")))
def test_shipped_specs_load_and_dry_run(name, tmp_path, monkeypatch):
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MPD_RUNS", str(tmp_path / "runs"))
    spec = load_spec(name)
    text = Runner(spec).describe()
    assert f"{len(spec.cells())} cells" in text
    for c in spec.cells():
        assert c.key in text


# ---------------------------------------------------------------------------------------------------- runs
def expected_rows(run_dir: Path) -> int:
    """Rows of a one-method run: the contexts of each scene (a context invalid with the extra objects is skipped
    there, and only there)."""
    man = json.loads((run_dir / "manifest.json").read_text())
    return sum(c["n_contexts"] for c in man["artifacts"][TASK]["contexts"].values())


def _run(spec_path: Path, run_dir: Path, **kw) -> pd.DataFrame:
    Runner(load_spec(spec_path), run_dir=run_dir, progress=False, **kw).run()
    return read_results(run_dir)


def test_provenance_columns_and_determinism(work):
    from mpd.data.definition import load_definition
    from mpd.provenance import git_state
    from mpd.tasks import load_task

    spec = write_spec(work, "det")
    a = _run(spec, work / "runs" / "det-a")
    b = _run(spec, work / "runs" / "det-b")
    n = expected_rows(work / "runs" / "det-a")
    assert 4 < n <= 2 * 4 and len(a) == n and a[["cell_key", "context_index"]].duplicated().sum() == 0
    pd.testing.assert_frame_equal(a[METRIC_COLUMNS], b[METRIC_COLUMNS])
    commit, dirty = git_state()
    lock = json.loads((load_definition(work / "tiny0.toml").data_dir / "lock.json").read_text())
    assert set(a["git_commit"]) == {commit} and set(a["git_dirty"]) == {dirty}
    assert set(a["task_hash"]) == {load_task(TASK).file_hash}
    assert set(a["dataset_hash"]) == {lock["content_hash"]}
    for col in ("spec_hash", "run_id", "torch_version", "libraries", "device", "time_total", "plan_seed"):
        assert col in a.columns and a[col].notna().all()
    man = json.loads((work / "runs" / "det-a" / "manifest.json").read_text())
    assert man["status"] == "completed" and man["n_rows"] == n
    # the pinned protocol: one content-addressed context file per scene, its hash in every row
    from mpd.data.eval_contexts import load_context_file

    files = man["artifacts"][TASK]["contexts"]
    assert set(files) == {"training", "extra-objects"} and files["training"]["n_skipped"] == 0
    assert set(a["contexts_hash"]) == {f["sha256"] for f in files.values()}
    for scene, f in files.items():
        cs = load_context_file(next((work / "cache" / "contexts").glob(f"{TASK}-{scene}-{f['sha256'][:16]}.npz")))
        rows = a[a["extra_objects"] == (scene == "extra-objects")]
        assert sorted(rows["context_index"]) == sorted(cs.index.tolist())
        assert sorted(f["skipped_index"] + cs.index.tolist()) == list(range(4))


def test_rerun_skips_finished_cells(work):
    spec = write_spec(work, "skip")
    run_dir = work / "runs" / "skip"
    first = _run(spec, run_dir)
    again = _run(spec, run_dir)
    pd.testing.assert_series_equal(first["finished_at"], again["finished_at"])


def test_resume_after_kill_9_loses_and_recomputes_nothing(work):
    spec = write_spec(work, "kill", n_contexts=10)
    run_dir = work / "runs" / "kill"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "mpd.cli", "run", str(spec), "--run-dir", str(run_dir)]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    store = RowStore(run_dir)
    deadline = time.time() + 240
    while time.time() < deadline and len(store.rows()) < 3:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = {(r["cell_key"], r["context_index"]): r["finished_at"] for r in store.rows()}
    assert 3 <= len(before) < 15, "the run should have been killed in the middle"
    subprocess.run(cmd, env=env, check=True, capture_output=True)
    df = read_results(run_dir)
    assert len(df) == expected_rows(run_dir) and not df[["cell_key", "context_index"]].duplicated().any()
    after = {(r.cell_key, r.context_index): r.finished_at for r in df.itertuples()}
    assert all(after[k] == v for k, v in before.items()), "a row finished before the kill was recomputed"


@pytest.mark.ray
def test_ray_and_local_give_identical_rows(work):
    pytest.importorskip("ray")
    spec = write_spec(work, "ray")
    local = _run(spec, work / "runs" / "ray-local")
    ray_df = _run(spec, work / "runs" / "ray-ray", executor="ray", workers=2)
    import ray

    ray.shutdown()
    skip = {c for c in local.columns if c.startswith(("time_", "info_"))} | {
        "finished_at",
        "run_id",
        "n_cost_gradient_calls",
    }
    cols = [c for c in local.columns if c not in skip]
    key = ["cell_key", "context_index"]
    pd.testing.assert_frame_equal(
        local.sort_values(key).reset_index(drop=True)[cols], ray_df.sort_values(key).reset_index(drop=True)[cols]
    )


def test_compare_same_runs_and_flag_changed_dataset(work):
    from mpd.experiments.tracking import compare_runs

    spec_a = write_spec(work, "cmp")
    a = work / "runs" / "cmp-a"
    b = work / "runs" / "cmp-b"
    _run(spec_a, a)
    _run(spec_a, b)
    table, notes = compare_runs(a, b)
    assert "no metric difference" in notes
    assert not table["inputs_changed"].astype(bool).any()
    spec_c = write_spec(work, "cmp", dataset="tiny1")  # same cells, another dataset
    c = work / "runs" / "cmp-c"
    _run(spec_c, c)
    table, notes = compare_runs(a, c)
    assert table["inputs_changed"].str.contains("dataset_hash").all()
    # the statistical comparison: a rerun on this machine reproduces the run, another dataset does not
    cmd = [sys.executable, "-m", "mpd.cli", "runs", "compare", "--equivalent"]
    same = subprocess.run([*cmd, str(a), str(b)], capture_output=True, text=True)
    assert same.returncode == 0, same.stderr
    assert "2 bit-identical (of 2 cells)" in same.stdout
    other = subprocess.run([*cmd, str(a), str(c)], capture_output=True, text=True)
    assert other.returncode == 1 and "dataset_hash changed in 2 cells" in other.stderr


def test_mlflow_run_appears_in_local_store(work):
    mlflow = pytest.importorskip("mlflow")
    pytest.importorskip("sqlalchemy")
    spec = write_spec(work, "mlf")
    run_dir = work / "runs" / "mlf"
    Runner(load_spec(spec), run_dir=run_dir, progress=False, mlflow=True).run()
    mlflow.set_tracking_uri(f"sqlite:///{work / 'runs' / 'mlflow.db'}")
    exp = mlflow.get_experiment_by_name("mpd")
    runs = mlflow.search_runs(experiment_ids=[exp.experiment_id], output_format="list")
    assert any(r.info.run_name == "mlf" for r in runs)
    # a training record (the runner logs the models it resolved, the training CLI with --mlflow)
    from mpd.experiments.tracking import log_model_to_mlflow

    meta = {
        "task_name": TASK,
        "kind": "diffusion",
        "parametrization": "bspline",
        "identity": "abc123",
        "dataset_hash": "d" * 64,
        "seed": 0,
        "training_spec": {"steps": 3, "batch_size": 2},
        "history": [{"step": 1, "train_loss": 1.0, "val_loss": 1.1}, {"step": 3, "train_loss": 0.5}],
        "final_train_loss": 0.5,
    }
    path = work / "meta.json"
    path.write_text(json.dumps(meta))
    rid = log_model_to_mlflow(path, f"sqlite:///{work / 'runs' / 'mlflow.db'}")
    assert rid is not None and log_model_to_mlflow(path, f"sqlite:///{work / 'runs' / 'mlflow.db'}") is None
    hist = mlflow.MlflowClient().get_metric_history(rid, "train_loss")
    assert [(m.step, m.value) for m in hist] == [(1, 1.0), (3, 0.5)]


def test_held_out_contexts_are_the_datasets_and_skipped_per_scene(work):
    """The pinned protocol: contexts are held-out forward paths of the dataset (test split first), far enough apart,
    chosen by the context seed; in the extra-objects scene exactly those invalid there (by the torch ground-truth
    checker with the clearance as margin, a second implementation) are skipped; files are content-addressed and a
    corrupted one is refused."""
    import numpy as np
    import torch

    from mpd.collision import CollisionChecker
    from mpd.data import eval_contexts as ec
    from mpd.data.dataset import SPLITS, load_dataset
    from mpd.tasks import load_task

    task = load_task(TASK)
    ds = load_dataset(work / "tiny0.toml")
    base = ec.task_contexts(task, ds, 6, seed=0)
    held = {int(c) for c in ds.context_id[(ds.split != SPLITS.index("train")) & ~ds.reversed]}
    assert set(base.context_id.tolist()) <= held
    for j, cid in enumerate(base.context_id):
        k = int(np.flatnonzero((ds.context_id == cid) & ~ds.reversed)[0])
        assert np.array_equal(base.q_start[j], ds.q_start[k]) and np.array_equal(base.q_goal[j], ds.q_goal[k])
    assert (np.linalg.norm(base.q_goal - base.q_start, axis=1) >= task.spec.context.min_start_goal_distance).all()
    other = ec.task_contexts(task, ds, 6, seed=1)
    assert set(other.context_id.tolist()) != set(base.context_id.tolist()), "the context seed picks the contexts"
    extra = ec.for_scene(base, task, True)
    chk = CollisionChecker(task, extra_objects=True, margin=task.spec.collision.clearance)
    ok = (chk.configs(torch.as_tensor(base.q_start)).valid & chk.configs(torch.as_tensor(base.q_goal)).valid).numpy()
    assert extra.index.tolist() == base.index[ok].tolist()
    assert extra.meta["skipped_index"] == base.index[~ok].tolist() and extra.meta["n_skipped"] == int((~ok).sum())
    again = ec.for_scene(base, task, True)
    assert again.hash == extra.hash and again.meta["path"] == extra.meta["path"]
    loaded = ec.load_context_file(extra.meta["path"])
    assert np.array_equal(loaded.q_start, extra.q_start) and loaded.meta["n_skipped"] == extra.meta["n_skipped"]
    bad = Path(extra.meta["path"]).with_name("corrupt-" + Path(extra.meta["path"]).name)
    arrays = extra.arrays()
    arrays["q_start"] = arrays["q_start"] + 1e-3
    np.savez(bad, **arrays)
    with pytest.raises(ValueError, match="does not match its hash"):
        ec.load_context_file(bad)
    with pytest.raises(ValueError, match="usable held-out contexts"):
        ec.task_contexts(task, ds, 1000)


def test_turned_contexts_turn_with_the_scene(work):
    """turn_contexts: in a rotated scene each context is its training-scene context turned about the base (start and
    goal by turn_configurations), those leaving the joint limits skipped and counted; without it the contexts stay."""
    import numpy as np
    import torch

    from mpd.data import eval_contexts as ec
    from mpd.data.dataset import load_dataset
    from mpd.tasks import load_task

    task = load_task(TASK)
    base = ec.task_contexts(task, load_dataset(work / "tiny0.toml"), 6, seed=0)
    turned = ec.for_scene(base, task, False, 40.0, turn=True)
    fixed = ec.for_scene(base, task, False, 40.0)
    assert turned.meta["turned"] and "turned" not in fixed.meta and turned.hash != fixed.hash
    inside = task.robot.within_limits(torch.as_tensor(ec.turn_configurations(task, base.q_start, 40.0)))
    inside &= task.robot.within_limits(torch.as_tensor(ec.turn_configurations(task, base.q_goal, 40.0)))
    assert turned.meta["n_outside_limits"] == int((~inside).sum())
    for j, i in enumerate(turned.index):
        k = int(np.flatnonzero(base.index == i)[0])
        want = ec.turn_configurations(task, base.q_start[k : k + 1], 40.0)[0]
        assert np.allclose(turned.q_start[j], want) and not np.allclose(turned.q_start[j], base.q_start[k])
    assert np.array_equal(ec.for_scene(base, task, False, 0.0, turn=True).q_start, base.q_start)


# ------------------------------------------------------------------------------------------ training axes
@pytest.mark.parametrize(
    ("axis", "values", "where"),
    [
        ('"training.lr_schedul"', '["wsd"]', "axes.training.lr_schedul"),
        ('"training.precision"', '["fp16"]', "axes.training.precision"),
        ('"training.steps"', "[0]", "axes.training.steps"),
        ('"training.lr"', '["fast"]', "axes.training.lr"),
        ('"model.unet_dim"', "[0]", "axes.model.unet_dim"),
        ('"model.unet_dim_mults"', "[[1, 2]]", "axes.model.unet_dim_mults"),
        ('"model.width"', "[16]", "axes.model.width"),
        ('"model.goal_head_width"', "[-1]", "axes.model.goal_head_width"),
        ('"model.context_init"', '["xavier"]', "axes.model.context_init"),
    ],
)
def test_bad_training_axes_name_the_axis(tmp_path, axis, values, where):
    p = write_spec(tmp_path, "bad", f"{axis} = {values}\n")
    with pytest.raises(ConfigError) as e:
        load_spec(p)
    assert str(p) in str(e.value) and where in str(e.value)


def test_training_axes_train_one_model_per_value_and_draw_learning_curves(work):
    """`training.*` and `model.*` axes: each budget is its own model (wsd: the longer resumes from the shorter's
    stable phase, of the same network only), the rows carry the model's steps and training time, methods without a
    model collapse the axes, and the report draws the learning curves and writes the recipe table."""
    from mpd.models.train import list_models
    from mpd.viz.report import build_report

    p = write_spec(
        work,
        "curves",
        axes={
            "method": ["gp-cost", "dprior"],
            "training.steps": [20, 40],
            "training.lr_schedule": ["wsd"],
            "training.precision": ["bf16"],
            "training.loss_weighting": ["uniform", "min_snr"],
            "model.unet_dim": [8, 16],
        },
    )
    spec = load_spec(p)
    cells = spec.cells()
    assert len([c for c in cells if c.p["method"] == "gp-cost"]) == 1  # the training axes collapse without a model
    assert len([c for c in cells if c.p["method"] == "dprior"]) == 8
    only = ["--only", "training.steps=20", "--only", "model.unet_dim=8", "--only", "method=dprior"]
    r = subprocess.run(
        [sys.executable, "-m", "mpd.cli", "run", str(p), "--dry-run", *only], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("method=dprior") == 2  # the two loss weightings of the 20-step, width-8 models
    run_dir = work / "runs" / "curves"
    df = _run(p, run_dir, workers=2)
    dp = df[df["method"] == "dprior"]
    keys = ["training.loss_weighting", "training.steps", "model.unet_dim"]
    assert dp.groupby(keys)["model_id"].nunique().eq(1).all()
    assert dp["model_id"].nunique() == 8 and set(dp["model_steps"]) == {20, 40}
    assert (df.loc[df["method"] == "gp-cost", "model_id"] == "").all()
    metas = {m["identity"]: m for m in list_models(TASK)}
    for ident, g in dp.groupby("model_id"):
        meta = metas[ident]
        assert meta["training_spec"]["precision"] == "bf16" and meta["training_spec"]["lr_schedule"] == "wsd"
        assert meta["model_spec"]["unet_dim"] == int(g["model.unet_dim"].iloc[0])
        assert float(g["model_train_s"].iloc[0]) == pytest.approx(meta["wall_time_s"])
        # the 40-step budget of each recipe resumed from the 20-step one's stable phase (step 16)
        assert meta.get("resumed_from_trunk_step") == (16 if meta["step"] == 40 else None)
    index = build_report(run_dir, recordings=False)
    text = (index.parent / "training.md").read_text()
    assert "loss_weighting=min_snr" in text and "loss_weighting=uniform" in text and "model.unet_dim=8" in text
    # the training and network axes name cells when runs are compared and summarised (they were merged before)
    from mpd.experiments.reproduce import compare
    from mpd.experiments.tracking import cell_summary

    comp = compare(run_dir, run_dir)
    assert len(comp.cells) == 9 and (comp.cells["level"] == "bit-identical").all()
    assert len(cell_summary(df)) == 9
    assert (index.parent / "figures" / "learning_curves.png").stat().st_size > 10_000


@pytest.mark.slow  # compiles the 2-D network once (~20-40 s on 2 cores)
def test_spec_runs_compile_the_network_by_default_before_the_first_timed_plan(work, monkeypatch):
    """Without a setting, a spec run's diffusion planners run the compiled network (bf16 where the CPU has it),
    compiled before the first timed plan (time_warmup in that row only); methods without a network and
    ``fast = false`` run as before; MPD_COMPILE=0 turns it off."""
    from mpd.device import network_precision

    monkeypatch.delenv("MPD_COMPILE", raising=False)
    p = write_spec(
        work,
        "fast",
        n_contexts=3,
        axes={"method": ["gp-cost", "dprior"], "training.steps": [20], "model.unet_dim": [8]},
    )
    df = _run(p, work / "runs" / "fast")
    dp, gp = df[df["method"] == "dprior"], df[df["method"] == "gp-cost"]
    assert dp["info_network_compiled"].eq(True).all()
    assert set(dp["info_network_precision"]) == {network_precision("auto", "cpu")}
    assert "info_network_compiled" not in gp or not gp["info_network_compiled"].eq(True).any()
    warm = dp.sort_values("finished_at")["time_warmup"].to_numpy()
    assert warm[0] > 0 and (warm[1:] == 0).all()  # compiled once, in front of the first plan
    assert dp["time_total"].max() < warm[0]  # and never inside a timed plan
    # fast = false, or MPD_COMPILE=0: the eager network, nothing compiled
    plan = load_spec(p).cells()
    assert plan  # the spec is unchanged but for the switch below
    p.write_text(p.read_text().replace('name = "fast"', 'name = "eager"\nfast = false'))
    eager = _run(p, work / "runs" / "eager")
    assert not eager.loc[eager["method"] == "dprior", "info_network_compiled"].any()
    assert (eager["time_warmup"] == 0).all()


def test_a_run_made_in_parts_keeps_every_parts_tasks_cells_and_artifacts(work):
    """`--only task=A`, then `--only task=B` into one run folder: the manifest names both tasks' files, cells and
    artifacts (dataset and its hash), as the rows do (the second part once overwrote the first's artifacts)."""
    narrow = "EnvNarrowPassageDense2D-RobotPointMass2D"
    (work / "tinyn.toml").write_text((work / "tiny0.toml").read_text().replace(TASK, narrow).replace("tiny0", "tinyn"))
    p = write_spec(work, "parts", n_contexts=2)
    p.write_text(
        p.read_text()
        .replace(f'task = ["{TASK}"]', f'task = ["{TASK}", "{narrow}"]')
        .replace("extra_objects = [false, true]", "extra_objects = [false]")
        + f'[tasks."{narrow}"]\ndataset = "{work / "tinyn"}.toml"\n'
    )
    run_dir = work / "runs" / "parts"
    for task in (TASK, narrow):
        Runner(load_spec(p), only={"task": [task]}, run_dir=run_dir, progress=False).run()
    m = json.loads((run_dir / "manifest.json").read_text())
    df = read_results(run_dir)
    assert set(df["task"]) == {TASK, narrow} == set(m["artifacts"]) == set(m["task_files"])
    assert {c["task"] for c in m["cells"]} == {TASK, narrow} and len(m["cells"]) == 2
    for task, g in df.groupby("task"):
        assert set(g["dataset_hash"]) == {m["artifacts"][task]["dataset_hash"]}
    # a folder reused for another spec starts its manifest afresh
    q = write_spec(work, "parts2", n_contexts=2)
    Runner(load_spec(q), run_dir=run_dir, progress=False).run()
    assert set(json.loads((run_dir / "manifest.json").read_text())["task_files"]) == {TASK}


def test_parts_by_method_keep_every_model_of_a_task_in_the_manifest():
    """`--only method=dprior`, then `--only method=cvae` into one folder: the task's manifest entry names both models
    and their sources (the second part once replaced the first's models); a part on another dataset of the task
    replaces the entry (its models belong to other data), and other tasks' entries are kept."""
    from mpd.experiments.runner import merge_artifacts

    def art(dataset, models, sources, scenes):
        return {
            "task_hash": "t",
            "dataset_hash": dataset,
            "dataset_source": "digest",
            "models": models,
            "model_sources": sources,
            "contexts": {s: {"sha256": s} for s in scenes},
        }

    first = {
        "A": art("d1", {"diffusion-bspline": "m1"}, {"diffusion-bspline": "shipped"}, ["training"]),
        "B": art("d9", {"diffusion-bspline": "m9"}, {"diffusion-bspline": "cache"}, ["training"]),
    }
    second = {"A": {**art("d1", {"cvae-bspline": "m2"}, {"cvae-bspline": "cache"}, ["extra-objects"]),
                    "dataset_source": "cache"}}  # fmt: skip
    m = merge_artifacts(first, second)
    assert m["A"]["models"] == {"diffusion-bspline": "m1", "cvae-bspline": "m2"}
    assert m["A"]["model_sources"] == {"diffusion-bspline": "shipped", "cvae-bspline": "cache"}
    assert set(m["A"]["contexts"]) == {"training", "extra-objects"}
    assert m["A"]["dataset_source"] == "cache" and m["B"] == first["B"]
    other = {"A": art("d2", {"cvae-bspline": "m3"}, {"cvae-bspline": "cache"}, ["training"])}
    assert merge_artifacts(first, other)["A"] == other["A"]
    assert first["A"]["models"] == {"diffusion-bspline": "m1"}  # the inputs are not modified


def test_training_chains_join_the_budgets_of_one_recipe_and_one_network_only():
    """The wsd budgets of one recipe train in one worker (the longer resumes from the shorter's stable phase); two
    networks or two recipes are separate chains that train in parallel (two widths were once one serial chain)."""
    from mpd.experiments.artifacts import _chain_key, model_settings, training_settings
    from mpd.experiments.spec import TaskSettings
    from mpd.tasks import load_task

    task = load_task(TASK)
    ts = TaskSettings(dataset="EnvSimple2D-RobotPointMass2D-paper", profile="cpu")

    def job(**over):
        over = tuple(sorted(over.items()))
        return (TASK, "diffusion", "bspline", None, model_settings(task, over), training_settings(task, ts, over), over)

    short, long = job(steps=3000), job(steps=6000)
    assert _chain_key(short) == _chain_key(long)
    assert _chain_key(short) != _chain_key(job(**{"steps": 3000, "model.unet_dim": 16}))
    assert _chain_key(short) != _chain_key(job(steps=3000, lr=2e-3))
    assert _chain_key(job(lr_schedule="cosine")) != _chain_key(job(lr_schedule="cosine"))


def test_a_model_of_its_own_profile_trains_beside_the_task_profile_models(tmp_path):
    """`[tasks."NAME".models."diffusion-bspline"]`: that prior takes its own profile and step count (its identity is
    the one `mpd train --profile P --steps N` gives), the task's other models keep the task's profile; the
    "<kind>-<parametrization>" entry wins over the "<kind>" one field by field; --scale shrinks its steps too."""
    from mpd.experiments.artifacts import _model_identity, training_settings
    from mpd.experiments.spec import ModelProfile, TaskSettings, scale_spec
    from mpd.tasks import load_task

    p = write_spec_file(
        tmp_path / "own.toml",
        axes={"task": [TASK], "method": ["dprior", "cvae"], "parametrization": ["bspline", "waypoints"]},
        tasks={
            TASK: {
                "dataset": f"{TASK}-paper",
                "models": {
                    "diffusion-bspline": {"profile": "paper", "train_steps": 55000},
                    "diffusion": {"train_steps": 7000},
                },
            }
        },
        name="own",
    )
    spec = load_spec(p)
    ts, task = spec.data.tasks[TASK], load_task(TASK)
    assert (ts.profile_for("diffusion", "bspline"), ts.steps_for("diffusion", "bspline")) == ("paper", 55000)
    assert (ts.profile_for("diffusion", "waypoints"), ts.steps_for("diffusion", "waypoints")) == ("cpu", 7000)
    assert (ts.profile_for("cvae", "bspline"), ts.steps_for("cvae", "bspline")) == ("cpu", None)
    paper = training_settings(task, ts, (), "diffusion", "bspline")
    assert paper.steps == 55000 and paper.lr == task.training("paper").lr != task.training("cpu").lr
    assert training_settings(task, ts, (), "cvae", "bspline") == task.training("cpu")
    content = "0" * 64
    alone = {
        ("diffusion", "bspline"): TaskSettings(dataset="d", profile="paper", train_steps=55000),
        ("diffusion", "waypoints"): TaskSettings(dataset="d", train_steps=7000),
        ("cvae", "bspline"): TaskSettings(dataset="d"),
    }
    for (kind, par), other in alone.items():
        assert _model_identity(task, ts, content, kind, par, ()) == _model_identity(task, other, content, kind, par, ())
    assert _model_identity(task, ts, content, "diffusion", "bspline", ()) != _model_identity(
        task, alone[("diffusion", "waypoints")], content, "diffusion", "bspline", ()
    )
    small = scale_spec(spec, 1e-3).data.tasks[TASK]
    assert small.models == {
        "diffusion-bspline": ModelProfile(profile="paper", train_steps=55),
        "diffusion": ModelProfile(train_steps=20),
    }
    assert small.steps_for("cvae", "bspline") == 24  # the task's (cpu) 24000 x 1e-3


# ------------------------------------------------------------------------------------- shipped evaluation inputs
def test_shipped_priors_and_digest_evaluate_without_generating_the_dataset(work, tmp_path, monkeypatch, capfd):
    """A fresh cache with the dataset's digest and its model shipped: the run generates no dataset and trains
    nothing, and its rows are the rows of the run that generated and trained them (timings aside). A digest that
    does not match its record is named and not used."""
    from mpd.data import digest
    from mpd.data.dataset import load_dataset
    from mpd.data.definition import load_definition
    from mpd.data.generate import generate
    from mpd.experiments.artifacts import data_range
    from mpd.models import shipped
    from mpd.models.train import list_models
    from mpd.tasks import load_task

    # a definition of its own, with the lock next to it that `mpd data generate` writes (and a repo commits)
    (tmp_path / "dg.toml").write_text((work / "tiny0.toml").read_text().replace('name = "tiny0"', 'name = "dg"'))
    spec = write_spec_file(
        tmp_path / "dg-eval.toml",
        axes={"task": [TASK], "method": ["gp-cost", "dprior"], "extra_objects": [False, True]},
        tasks={TASK: {"dataset": f"{tmp_path / 'dg.toml'}", "profile": "cpu", "train_steps": 20}},
        name="dg-eval",
        n_contexts=4,
        n_samples=16,
        seeds=[0],
        record_contexts=0,
    )
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "a"))
    monkeypatch.setenv("MPD_PRIORS", "none")
    generate(load_definition(tmp_path / "dg.toml"), workers=1, progress=False)
    assert (tmp_path / "dg.lock.json").is_file()
    a = _run(spec, tmp_path / "runs" / "a")
    man_a = json.loads((tmp_path / "runs" / "a" / "manifest.json").read_text())["artifacts"][TASK]
    assert man_a["dataset_source"] == "cache" and set(man_a["model_sources"].values()) == {"trained"}
    ds = load_dataset(tmp_path / "dg.toml", generate_missing=False)
    task = load_task(TASK)
    (model,) = list_models(TASK)
    shipped.ship(model["path"], tmp_path / "priors")
    dg_path = digest.write(task, ds, data_range(task, ds), tmp_path / "priors")

    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "b"))
    monkeypatch.setenv("MPD_PRIORS", str(tmp_path / "priors"))
    text = Runner(load_spec(spec), run_dir=tmp_path / "runs" / "b").describe()
    assert "not needed: its shipped digest" in text and "ready (shipped prior)" in text and "nothing to build" in text
    b = _run(spec, tmp_path / "runs" / "b")
    assert not load_definition(tmp_path / "dg.toml").data_dir.exists(), "the dataset was generated"
    man_b = json.loads((tmp_path / "runs" / "b" / "manifest.json").read_text())["artifacts"][TASK]
    assert man_b["dataset_source"] == "digest" and set(man_b["model_sources"].values()) == {"shipped"}
    assert man_b["dataset_hash"] == man_a["dataset_hash"] and man_b["contexts"] == man_a["contexts"]
    key = ["cell_key", "context_index"]
    cols = [*METRIC_COLUMNS, "contexts_hash", "dataset_hash", "model_id", "plan_seed"]
    pd.testing.assert_frame_equal(
        a.sort_values(key).reset_index(drop=True)[key + cols], b.sort_values(key).reset_index(drop=True)[key + cols]
    )

    data = bytearray(dg_path.read_bytes())
    data[-200] ^= 0xFF  # one flipped byte among the stored contexts
    dg_path.write_bytes(bytes(data))
    capfd.readouterr()
    assert digest.find(TASK, "dg", man_a["dataset_hash"]) is None
    assert f"dataset digest {dg_path}" in capfd.readouterr().err
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "c"))
    text = Runner(load_spec(spec), run_dir=tmp_path / "runs" / "c").describe()
    assert "dataset  " in text and "to build (plan 64 contexts" in text


def test_eval_2d_cpu_on_a_fresh_clone_generates_and_trains_nothing(tmp_path, monkeypatch):
    """The committed report of eval-2d-cpu reproduces from a fresh clone in minutes: its datasets' shipped digests
    and its shipped priors cover every cell (an edit of a task file or of a training profile breaks this until
    the digest and the priors are shipped again: `mpd data digest`, `mpd models ship`)."""
    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MPD_RUNS", str(tmp_path / "runs"))
    monkeypatch.delenv("MPD_PRIORS", raising=False)
    needs = Runner(load_spec("eval-2d-cpu")).plan().needs
    assert all(n.exists for n in needs), "\n".join(n.describe() for n in needs if not n.exists)
    assert {n.detail for n in needs if n.kind == "dataset"} == {"digest"}
    assert {n.detail for n in needs if n.kind == "model"} == {"shipped"}


def test_scale_shrinks_every_cell_and_touches_nothing_full_size(tmp_path, monkeypatch):
    """`--scale`: the same matrix with fewer contexts, samples, steps and dataset contexts (with their floors), under
    a hash, run folder and dataset identities of its own; held-out contexts enough for its evaluation."""
    from mpd.experiments.spec import scale_spec

    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MPD_RUNS", str(tmp_path / "runs"))
    full = load_spec("paper-main")
    small = scale_spec(full, 1e-5)
    assert [c.p["method"] for c in small.cells()] == [c.p["method"] for c in full.cells()]
    assert small.hash != full.hash and small.name == "paper-main-x1e-05"
    assert {c.p["n_samples"] for c in small.cells()} == {8} and small.data.n_contexts == 2
    for name, ts in small.data.tasks.items():
        assert ts.train_steps in (20, 30)  # 2 M / 3 M paper steps x 1e-5, floor 20
        big, rd = full.definition(name), small.definition(name)
        assert rd.identity != big.identity and rd.name == f"{big.name}-x1e-05"
        d = rd.definition
        assert d.n_contexts == 128 and d.n_contexts // d.chunk_size >= 4
        assert (d.split.val + d.split.test) * d.n_contexts >= 16 * small.data.n_contexts
        assert not rd.lock_path.exists()
    assert scale_spec(full, 1.0) is full
    with pytest.raises(ConfigError, match="--scale"):
        scale_spec(full, 0)
    text = Runner(small).describe()
    assert "-x1e-05 [" in text and "train 20 steps" in text


def test_read_results_rebuilds_a_table_older_than_a_replaced_part(tmp_path):
    """Runs made in pieces and merged by copying parts: a part replaced by one of the same size (another run of the
    same cells) is newer than results.parquet, so the table is rebuilt from the parts, not the stale file read."""
    from mpd.experiments.results import write_parquet

    store = RowStore(tmp_path)
    for i in range(3):
        store.append("cellA", {"cell_key": "cellA", "context_index": i, "vendi": 1.0})
    write_parquet(store.table(), tmp_path / "results.parquet")
    assert read_results(tmp_path).vendi.tolist() == [1.0, 1.0, 1.0]
    old = (tmp_path / "results.parquet").stat().st_mtime
    part = tmp_path / "parts" / "cellA.jsonl"
    part.write_text(
        "".join(json.dumps({"cell_key": "cellA", "context_index": i, "vendi": 7.0}) + "\n" for i in range(3))
    )
    os.utime(part, (old + 5, old + 5))
    assert read_results(tmp_path).vendi.tolist() == [7.0, 7.0, 7.0]
    os.utime(tmp_path / "results.parquet", (old + 10, old + 10))  # a table written after the parts is read as is
    assert read_results(tmp_path).vendi.tolist() == [1.0, 1.0, 1.0]


def test_cvae_profile_trains_the_cvae_of_another_profile_than_the_diffusion_prior(tmp_path, monkeypatch):
    """eval-panda-gpu-priors: the diffusion priors of the `gpu` profile (shipped) beside the CVAE of the `cpu` one;
    the identities are the ones each profile gives alone (the CVAE is eval-panda-cpu's, the priors the shipped ones)."""
    from mpd.experiments.artifacts import _model_identity, training_settings
    from mpd.experiments.spec import TaskSettings
    from mpd.tasks import load_task

    monkeypatch.setenv("MPD_CACHE", str(tmp_path / "cache"))
    gpu, cpu = load_spec("eval-panda-gpu-priors"), load_spec("eval-panda-cpu")
    for name in ("EnvSpheres3D-RobotPanda", "EnvWarehouse-RobotPanda"):
        task, ts, ts_cpu = load_task(name), gpu.data.tasks[name], cpu.data.tasks[name]
        assert (ts.profile_for("diffusion"), ts.profile_for("cvae")) == ("gpu", "cpu")
        assert training_settings(task, ts, (), "cvae") == task.training("cpu")
        assert training_settings(task, ts, (), "diffusion") == task.training("gpu")
        content = "0" * 16
        assert _model_identity(task, ts, content, "cvae", "bspline", ()) == _model_identity(
            task, ts_cpu, content, "cvae", "bspline", ()
        )
        assert _model_identity(task, ts, content, "diffusion", "bspline", ()) != _model_identity(
            task, ts_cpu, content, "diffusion", "bspline", ()
        )
    assert TaskSettings(dataset="d", profile="gpu").profile_for("cvae") == "gpu"
    needs = Runner(gpu).plan().needs
    shipped = {n.name for n in needs if n.kind == "model" and n.detail == "shipped"}
    assert any("58965bec51b8e17a" in s for s in shipped) and any("101f5acb14ab5f94" in s for s in shipped), shipped
