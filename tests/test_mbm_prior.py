"""MPD on MotionBenchMaker's problems: a dataset whose contexts are benchmark problems (each planned in its own
scene), a prior trained on it, and the prior's planner on held-out problems, its runs beside RRTConnect's in one OMPL
benchmark database that Planner Arena's own loader reads."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest
import torch

from mpd.data import mbm
from mpd.paths import DATASETS_DIR
from tests.test_models import TINY, tiny_training

pytestmark = pytest.mark.usefixtures("one_thread")

TASK = DATASETS_DIR / "mbm" / "MBM-RobotPanda.toml"
DEFINITION = """name = "{name}"
task = "{task}"
n_contexts = 8
chunk_size = 4
seed = 0
[planner]
max_checks = 60000
time_limit = 60.0
[problems]
families = ["bookshelf_small", "cage"]
first = 1
last = {last}
"""


def _definition(tmp_path, last: int = 2):
    from mpd.data.definition import load_definition

    path = tmp_path / f"mbm-tiny-{last}.toml"
    path.write_text(DEFINITION.format(name=path.stem, task=TASK, last=last))
    return load_definition(path)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from mpd.data.dataset import load_dataset

    tmp = tmp_path_factory.mktemp("mbm-data")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MPD_CACHE", str(tmp / "cache"))
        rd = _definition(tmp)
        ds = load_dataset(rd, workers=1, progress=False, create_lock=False)
        yield tmp, rd, ds


def test_a_dataset_of_benchmark_problems_plans_each_in_its_own_scene(data):
    from mpd.collision import CollisionChecker
    from mpd.data.generate import problem_list
    from mpd.data.storage import read_chunk
    from mpd.experiments.mbm import _densify

    tmp, rd, ds = data
    problems = problem_list(rd)
    assert [p.name for p, _ in problems] == [
        "bookshelf_small/0001", "bookshelf_small/0002", "cage/0001", "cage/0002"
    ]  # fmt: skip
    # the cage goals close the hand on the cube: left out of the scene, like the baseline's grasp_target="ignored"
    assert [left for _, left in problems][2:] == ["Cube1", "Cube1"]
    chunks = [read_chunk(rd.data_dir, i) for i in range(2)]
    stored = {k: np.concatenate([c[k] for c in chunks]) for k in ("q_start", "q_goal", "status", "path", "success")}
    # context i is problem i mod 4, planned with its own seed: a repeat is another path between the same ends
    for i in range(8):
        p, left = problems[i % 4]
        np.testing.assert_array_equal(stored["q_start"][i], p.start)
        np.testing.assert_array_equal(stored["q_goal"][i], p.goal)
    assert stored["success"].all(), stored["status"]
    # (bookshelf_small/0001 is one straight edge, the same for every seed; the cage's are not)
    assert not np.allclose(stored["path"][2], stored["path"][6]) and not np.allclose(
        stored["path"][3], stored["path"][7]
    )
    # each path is collision free in its own problem's scene, checked densely by the ground truth; the cage paths
    # are not in the scene of a bookshelf (they were planned around the cage, not in an empty scene)
    task = rd.task

    def valid_in(k: int, path) -> bool:
        p, left = problems[k]
        env = task.env().with_obstacles(p.primitives(without=left))
        dense = torch.as_tensor(_densify(np.asarray(path, dtype=np.float64), 0.02))
        v = CollisionChecker(task, env=env, margin=0.0).configs(dense)
        # (collisions only: a goal on a joint limit, stored in float32, can lie a rounding beyond it)
        return bool((v.env_free & v.self_free).all())

    assert all(valid_in(i % 4, stored["path"][i]) for i in range(8))
    # the dataset as training sees it: both directions of each path, the problems' contexts
    assert len(ds) == 16 and ds.fit_free.mean() > 0.5
    # the problems enter the identity: another range of problems is another dataset
    assert _definition(tmp, last=3).identity != rd.identity


def test_an_invalid_definition_of_problems_names_the_field(tmp_path):
    from mpd.data.definition import load_definition
    from mpd.schema import ConfigError

    path = tmp_path / "bad.toml"
    path.write_text(DEFINITION.format(name="bad", task=TASK, last=2).replace('"cage"', '"kitchen"'))
    with pytest.raises(ConfigError, match="kitchen"):
        load_definition(path)
    path.write_text(DEFINITION.format(name="bad", task=TASK, last=101))
    with pytest.raises(ConfigError, match="last"):
        load_definition(path)


@pytest.fixture(scope="module")
def prior(data):
    from mpd.models.data import training_arrays
    from mpd.models.train import train_model

    tmp, rd, ds = data
    arrays = training_arrays(rd.task, ds, "bspline")
    return train_model(arrays, "diffusion", TINY, tiny_training(), progress=False, cache=tmp / "models", shipped=False)


def test_a_prior_plans_held_out_problems_and_joins_rrtconnect_in_one_database(data, prior, tmp_path):
    from mpd import bench
    from mpd.experiments import mbm as mbm_run

    imported = mbm.import_problems(root=tmp_path / "import")
    settings = mbm_run.PriorSettings(method="mpd", model=str(prior), n_samples=4, first=51, last=51, fast=False)
    out = tmp_path / "mpd"
    recs = bench.run_prior(imported, out, settings, ("bookshelf_small", "cage"))
    assert [(r["family"], r["index"]) for r in recs] == [("bookshelf_small", 51), ("cage", 51)]
    assert [r["left_out"] for r in recs][1] == "Cube1"
    for r in recs:
        assert r["status"] in ("ok", "no_valid") and r["time_s"] > 0 and r["n_samples"] == 4
        assert r["success"] == (r["fraction_valid"] > 0) == r["valid_mpd"]
        assert (r["path_length"] is None) == (not r["success"])
    # resumable; other settings need another folder
    lines = (out / mbm_run.RESULTS).read_text()
    bench.run_prior(imported, out, settings, ("bookshelf_small", "cage"))
    assert (out / mbm_run.RESULTS).read_text() == lines
    with pytest.raises(ValueError, match="other settings"):
        bench.run_prior(imported, out, mbm_run.PriorSettings(model=str(prior), n_samples=8, first=51, last=51))
    # a start or goal the checker refuses is a record, not an error: problem 51 of table_pick with the can in place
    # is valid, so take a goal beyond mpd's joint limits
    task = bench.load_prior_planner(settings).task
    lo = task.robot.q_min.numpy()
    p = imported.problems("table_pick")[50]
    bad = mbm.Problem(p.family, p.index, p.start, tuple(lo - 0.1), p.obstacles)
    r = bench.run_prior_problem(bench.load_prior_planner(settings), "table_pick", bad, settings)
    assert (r["status"], r["success"], r["time_first_s"]) == ("invalid_goal", False, None)

    # RRTConnect's run folder and the prior's in one database: two planner configurations per family
    rrt = tmp_path / "rrt"
    mbm_run.run_baseline(imported, rrt, mbm_run.BaselineSettings(time_limit=5.0), ("bookshelf_small", "cage"), 1)
    db = mbm_run.write_database(out, tmp_path / "both.db", more=(rrt,))
    conn = sqlite3.connect(db)
    configs = [row[1] for row in conn.execute("SELECT * FROM plannerConfigs ORDER BY id")]
    assert configs == ["mpd_mpd", "geometric_RRTConnect"]
    runs = conn.execute(
        "SELECT e.name, p.name, r.problem, r.solved, r.fraction_valid FROM runs r "
        "JOIN experiments e ON r.experimentid = e.id JOIN plannerConfigs p ON r.plannerid = p.id ORDER BY r.id"
    ).fetchall()
    conn.close()
    assert [(e, p, i) for e, p, i, _, _ in runs] == [
        ("mbm_panda_bookshelf_small", "mpd_mpd", 51),
        ("mbm_panda_bookshelf_small", "geometric_RRTConnect", 1),
        ("mbm_panda_cage", "mpd_mpd", 51),
        ("mbm_panda_cage", "geometric_RRTConnect", 1),
    ]
    assert [fv for *_, fv in runs][::2] == [pytest.approx(r["fraction_valid"]) for r in recs]
    assert all(fv is None for *_, fv in runs[1::2])
    side = json.loads((tmp_path / mbm_run.SIDECAR).read_text())
    assert [p["planner"] for p in side["planners"]] == ["mpd_mpd", "geometric_RRTConnect"]
    assert side["families"]["mpd_mpd"]["cage"]["problems"] == 1

    database = pytest.importorskip("plannerarena.database", reason="plannerarena (the dev extra) is not installed")
    loaded = database.load_database(db)
    assert loaded["problem_names"] == ["mbm_panda_bookshelf_small", "mbm_panda_cage"]
    assert "fraction valid" in loaded["attributes"]
    assert loaded["runs"].height == 4 and len(set(loaded["runs"]["planner"].cast(str).to_list())) == 2
    # the held-out problems only: RRTConnect's runs of problem 1 are left out
    held_out = mbm_run.write_database(out, tmp_path / "held-out.db", more=(rrt,), problems=(51, 100))
    conn = sqlite3.connect(held_out)
    kept = conn.execute("SELECT r.problem, p.name FROM runs r JOIN plannerConfigs p ON r.plannerid = p.id").fetchall()
    conn.close()
    assert sorted(kept) == [(51, "mpd_mpd"), (51, "mpd_mpd")]


def test_float32_within_keeps_a_configuration_on_a_limit_on_it():
    from mpd.planners.inputs import float32_within

    rng = np.random.default_rng(0)
    lo, hi = np.full(5000, -2.8973), np.full(5000, 2.8973)
    q = np.where(rng.random(5000) < 0.5, lo, hi) + rng.normal(0, 1e-7, 5000) * (rng.random(5000) < 0.5)
    q = np.clip(q, lo, hi)
    plain = q.astype(np.float32).astype(np.float64)
    assert ((plain < lo) | (plain > hi)).any()  # the plain cast rounds some beyond
    x = float32_within(q, lo, hi)
    assert x.dtype == np.float32 and ((x >= lo) & (x <= hi)).all()
    # the nearest float32 inside: at most one float32 spacing from the plain cast, equal to it where that is inside
    assert (np.abs(x - plain) <= np.spacing(np.float32(2.9))).all()
    inside = (plain >= lo) & (plain <= hi)
    np.testing.assert_array_equal(x[inside], plain[inside])


def test_a_goal_on_a_joint_limit_ends_every_trajectory_within_the_limits(prior):
    """Many MBM goals lie on a joint limit (180 of 700 round beyond it in float32): the plan's trajectories end on
    the goal, within the limits."""
    from mpd.api import Box, load_planner
    from mpd.experiments.mbm import PRIOR_TASK

    imported = mbm.import_problems()
    planner = load_planner(PRIOR_TASK, "dprior", model=str(prior), fast=False)
    lo, hi = planner.task.robot.q_min.double().numpy(), planner.task.robot.q_max.double().numpy()
    for p in imported.problems("cage"):
        g = np.asarray(p.goal, dtype=np.float32).astype(np.float64)
        if ((g < lo) | (g > hi)).any():
            break
    left = mbm.grasped_object(p, mbm.grasp_points(planner.task.robot, [p.goal])[0])
    boxes = [Box(b.centre, b.half_size, rotation=b.rotation) for b in p.primitives(without=left)]
    plan = planner.plan(p.start, p.goal, obstacles=boxes, n_samples=4, seed=0)
    end = plan.q[:, -1]
    assert ((end >= lo) & (end <= hi)).all()
    np.testing.assert_allclose(end, np.broadcast_to(p.goal, end.shape), atol=1e-6)


def test_a_plan_time_scene_s_truncated_grid_is_exact_below_tau_and_leaves_the_cost_unchanged():
    """The grid of obstacles given at plan time is built around the objects only (a truncated SDF): exact below
    PLAN_TIME_GRID_TRUNCATION, and the collision cost (value and gradient) the same as on the full grid."""
    from mpd.costs import CostFunction
    from mpd.envs.environment import PLAN_TIME_GRID_TRUNCATION as TAU
    from mpd.envs.grid import GridSDF
    from mpd.tasks import load_task
    from mpd.trajectory import make_parametrization

    task = load_task(TASK)
    p = mbm.import_problems().problems("cage")[50]
    env = task.env().with_obstacles(p.primitives())
    truncated = env.grid("extra")
    assert truncated.truncate == TAU
    full = GridSDF(env.extra, *env.workspace, task.spec.environment.sdf_cell_size)
    a, b = truncated._packed, full._packed
    near = b[:, 0] < TAU
    assert 0.02 < near.float().mean() < 0.5
    torch.testing.assert_close(a[near], b[near], rtol=0, atol=0)
    assert (a[~near, 0] == TAU).all()
    # the collision cost of random trajectories around the cage, on each grid
    param = make_parametrization(task, "bspline")
    rng = torch.Generator().manual_seed(0)
    B, n_free = 64, param.n_free
    q_start = torch.as_tensor(p.start, dtype=torch.float32).expand(B, -1)
    q_goal = torch.as_tensor(p.goal, dtype=torch.float32).expand(B, -1)
    s = torch.linspace(0, 1, n_free + 2)[1:-1, None]
    free = q_start[:, None] * (1 - s) + q_goal[:, None] * s + 0.6 * torch.randn(B, n_free, task.dof, generator=rng)
    results = []
    for grid in (truncated, full):
        e = task.env().with_obstacles(p.primitives())
        e._grids["extra"] = grid
        results.append(CostFunction(task, param, e, preset="official", sdf_mode="nearest")(free, q_start, q_goal))
    (rt, rf) = results
    assert (rf.values["collision"] > 0).sum() > B // 4  # the trajectories do touch the cage
    torch.testing.assert_close(rt.total, rf.total, rtol=0, atol=0)
    torch.testing.assert_close(rt.grad, rf.grad, rtol=0, atol=0)
