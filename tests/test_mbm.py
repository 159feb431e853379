"""MotionBenchMaker's Panda problems: the import (counts, stored form, frames), the validity of starts and goals under
mpd's checker (the grasped object an obstacle or left out), the RRTConnect baseline (resumable) and its OMPL
benchmark database, read back by Planner Arena's own loader."""

from __future__ import annotations

import hashlib
import json
import sqlite3
import subprocess

import numpy as np
import pytest
import torch

from mpd.data import benchmark_db, mbm
from mpd.envs.primitives import ObjectSet

# the shipped archive, as found in vamp-planner 0.6.4's source package: (problems, cylinders, boxes) per family
COUNTS = {
    "table_pick": (100, 200, 1000),
    "table_under_pick": (100, 200, 1000),
    "box": (100, 100, 600),
    "bookshelf_small": (100, 300, 400),
    "bookshelf_tall": (100, 900, 600),
    "bookshelf_thin": (100, 1000, 1100),
    "cage": (100, 0, 800),
}
# goals valid under mpd's checker (cylinders as 4 boxes). Every start is valid. Invalid goals: the hand's spheres,
# which fill the gap between mpd's fingers, in the grasped can from above (box) or around the grasped cube (cage);
# 2 + 2 goals beyond mpd's joint limits (the datasheet's, narrower than MBM's URDF), 1 in the table (table_pick).
GOALS_VALID = {
    "table_pick": 97,
    "table_under_pick": 98,
    "box": 51,
    "bookshelf_small": 100,
    "bookshelf_tall": 100,
    "bookshelf_thin": 100,
    "cage": 0,
}

# with the grasped object left out of the scene (grasp_target="ignored"): every box and cage goal is valid; the table
# goals beyond mpd's joint limits and the one in the table stay invalid
GOALS_VALID_IGNORED = {**GOALS_VALID, "box": 100, "cage": 100}


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    return mbm.import_problems(root=tmp_path_factory.mktemp("mbm"))


def test_the_shipped_archive_is_the_one_of_the_source_package():
    assert hashlib.sha256(mbm.SHIPPED.read_bytes()).hexdigest() == mbm.SHIPPED_SHA256
    assert (mbm.SHIPPED.parent / "LICENSE-vamp.txt").read_text().lstrip().startswith("Apache License")


def test_import_counts_and_identity(imported, tmp_path):
    assert imported.families == mbm.FAMILIES
    index = json.loads((imported.root / "index.json").read_text())
    assert index["source_sha256"] == mbm.SHIPPED_SHA256 and imported.root.name == f"panda-{imported.identity}"
    for fam, (n, n_cyl, n_box) in COUNTS.items():
        ps = imported.problems(fam)
        assert len(ps) == index["families"][fam]["problems"] == n
        assert [p.index for p in ps] == list(range(1, 101))
        kinds = [o.kind for p in ps for o in p.obstacles]
        assert (kinds.count("cylinder"), kinds.count("box"), kinds.count("sphere")) == (n_cyl, n_box, 0)
        # every request starts from MBM's "ready" pose, but table_under_pick's, which start anywhere
        starts = {p.start for p in ps}
        ready = {(0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)}
        assert len(starts) == 100 and not starts & ready if fam == "table_under_pick" else starts == ready
    # a second import of the same archive finds its files and keeps them
    before = {f.name: f.stat().st_mtime_ns for f in imported.root.iterdir()}
    again = mbm.import_problems(root=imported.root.parent)
    assert again == imported and {f.name: f.stat().st_mtime_ns for f in imported.root.iterdir()} == before
    # a damaged family file is rewritten
    (imported.root / "cage.json").write_text("{}")
    mbm.import_problems(root=imported.root.parent, families=("cage",))
    assert len(imported.problems("cage")) == 100


def test_moveit_yaml_conventions():
    """Orientation (x, y, z, w), box sizes as full side lengths, cylinder dimensions (height, radius)."""
    s = 0.5**0.5
    scene = {
        "world": {
            "collision_objects": [
                {
                    "id": "b",
                    "primitives": [{"type": "box", "dimensions": [0.4, 0.2, 0.1]}],
                    "primitive_poses": [{"position": [1, 2, 3], "orientation": [0, 0, s, s]}],  # 90 deg about z
                },
                {
                    "id": "c",
                    "primitives": [{"type": "cylinder", "dimensions": [0.14, 0.03]}],
                    "primitive_poses": [{"position": [0, 0, 0], "orientation": [0, 0, 0, 1]}],
                },
            ]
        }
    }
    box, cyl = mbm.parse_scene(scene)
    assert box.half_extents == pytest.approx((0.2, 0.1, 0.05))
    assert box.rotation_wxyz == pytest.approx((s, 0, 0, s))
    (prim,) = box.primitives()
    assert prim.rotation @ np.array([1.0, 0, 0]) == pytest.approx([0, 1, 0], abs=1e-12)
    assert (cyl.kind, cyl.height, cyl.radius) == ("cylinder", 0.14, 0.03)


@pytest.mark.parametrize("slabs", [1, 2, 4, 8])
def test_cylinder_slabs_contain_the_cylinder_and_hug_it(slabs):
    r, h = 0.03, 0.14
    cyl = mbm.Obstacle("c", "cylinder", (0.3, -0.2, 0.5), radius=r, height=h, rotation_wxyz=(0.9, 0.1, -0.3, 0.2))
    rot = cyl.primitives(1)[0].rotation
    objs = ObjectSet(3, cyl.primitives(slabs))
    g = np.random.default_rng(slabs)
    n = 4000
    ang, z = g.uniform(0, 2 * np.pi, n), g.uniform(-h / 2, h / 2, n)
    rad = r * np.sqrt(g.uniform(0, 1, n))

    def world(rr, zz):
        return np.asarray(cyl.centre) + np.stack([rr * np.cos(ang), rr * np.sin(ang), zz], 1) @ rot.T

    inside = torch.as_tensor(world(rad, z))
    assert (objs.sdf(inside) <= 1e-12).all()
    # outside the cylinder by more than the slabs' largest excess: free
    excess = r * (np.sqrt(1 + np.sin(np.pi / (2 * slabs)) ** 2) - 1)
    outside = torch.as_tensor(world(np.full(n, r + excess + 1e-4), z))
    assert (objs.sdf(outside) > 0).all()


def test_frames_the_goal_grasps_its_object(imported):
    """MBM's goals are grasps: with both frames reconciled (MBM's world = mpd's, panda_link0 at the origin), the
    grasp point of mpd's hand (10.5 cm along its z axis, MBM's panda_grasptarget) lies within 2.5 cm of a can's axis
    (the box family grasps from above, just over the can's top) or within 5 cm of a cube's centre."""
    from mpd.envs.primitives import quat_wxyz_to_matrix
    from mpd.tasks import load_task

    robot = load_task(imported.task_path("cage")).robot
    for fam in mbm.FAMILIES:
        ps = imported.problems(fam)
        pos, rot = robot.ee_pose(torch.tensor([p.goal for p in ps], dtype=torch.float64))
        grasp = (pos + rot[..., 2] * 0.105).numpy()
        worst = 0.0
        for p, x in zip(ps, grasp):
            d = []
            for o in p.obstacles:
                local = quat_wxyz_to_matrix(o.rotation_wxyz).T @ (x - np.asarray(o.centre))
                if o.kind == "cylinder":
                    # distance to the can's axis (a segment)
                    d.append(np.hypot(np.linalg.norm(local[:2]), max(abs(local[2]) - o.height / 2, 0.0)))
                elif o.name.startswith("Cube"):
                    d.append(np.linalg.norm(local))
            worst = max(worst, min(d))
        assert worst < (0.05 if fam == "cage" else 0.025), fam


def test_starts_and_goals_under_mpds_checker(imported):
    for fam in mbm.FAMILIES:
        v = mbm.endpoint_validity(imported, fam)
        assert v["start_valid"].all(), fam
        assert int(v["goal_valid"].sum()) == GOALS_VALID[fam], fam
        assert v["goal_self_free"].all()
    # one circumscribed box per cylinder is too coarse for the grasps: the hand then touches its can
    v = mbm.endpoint_validity(imported, "bookshelf_small", cylinder_slabs=1)
    assert not v["goal_valid"].any()


def test_the_grasped_object_is_the_querys_candidate_at_the_grasp_point(imported):
    """MBM's queries name the candidates (Can1 on the tables and in the box, Cube1 in the cage, any can on the
    shelves); the goal's grasp point picks one, and leaving it out removes its primitives and no others."""
    from mpd.tasks import load_task

    robot = load_task(imported.task_path("cage")).robot
    for fam, expected in (("box", {"Can1"}), ("cage", {"Cube1"}), ("bookshelf_small", {"Can2", "Can3"})):
        ps = imported.problems(fam)
        names = {mbm.grasped_object(p, x) for p, x in zip(ps, mbm.grasp_points(robot, [p.goal for p in ps]))}
        assert names == expected, fam
    (p,) = [p for p in imported.problems("bookshelf_small") if p.index == 1]
    full = mbm.scene_primitives(p, robot)
    kept = mbm.scene_primitives(p, robot, "ignored")
    target = mbm.grasped_object(p, mbm.grasp_points(robot, [p.goal])[0])
    assert [q.name for q in full if not q.name.startswith(f"{target}#")] == [q.name for q in kept]
    assert len(full) - len(kept) == mbm.CYLINDER_SLABS
    with pytest.raises(ValueError, match="grasp_target"):
        mbm.scene_primitives(p, robot, "attached")


def test_with_the_grasped_object_left_out_every_box_and_cage_goal_is_valid(imported):
    for fam in ("box", "cage"):
        strict = mbm.endpoint_validity(imported, fam)
        loose = mbm.endpoint_validity(imported, fam, grasp_target="ignored")
        assert int(strict["goal_valid"].sum()) == GOALS_VALID[fam], fam  # the default is the strict reading
        assert int(loose["goal_valid"].sum()) == GOALS_VALID_IGNORED[fam] == 100, fam
        assert loose["start_valid"].all()


# the queries Planner Arena's loader (plannerarena.database.load_database) runs
ARENA_TABLES = ("experiments", "plannerConfigs", "enums", "runs", "progress")


def _baseline(imported, out):
    from mpd.experiments import mbm as mbm_run

    settings = mbm_run.BaselineSettings(time_limit=5.0, seed=0)
    for fam, limit in (("bookshelf_small", 2), ("cage", 1)):
        recs = mbm_run.run_baseline(imported, out, settings, (fam,), limit)
    return mbm_run, recs


def test_rrtconnect_results_resume_and_open_as_an_ompl_benchmark_database(imported, tmp_path):
    from mpd.data.planning import problem_seed

    mbm_run, recs = _baseline(imported, tmp_path)
    assert [(r["family"], r["index"], r["status"]) for r in recs] == [
        ("bookshelf_small", 1, "ok"),
        ("bookshelf_small", 2, "ok"),
        ("cage", 1, "invalid_goal"),
    ]
    for r in recs[:2]:
        assert r["success"] and r["valid_mpd"] and 0 < r["time_first_s"] <= r["time_s"]
        assert r["path_length"] > 0 and r["smoothness"] > 0
    # resumable: a rerun plans nothing again
    lines = (tmp_path / mbm_run.RESULTS).read_text()
    _baseline(imported, tmp_path)
    assert (tmp_path / mbm_run.RESULTS).read_text() == lines
    with pytest.raises(ValueError, match="other settings"):
        mbm_run.run_baseline(imported, tmp_path, mbm_run.BaselineSettings(time_limit=1.0))

    db = mbm_run.write_database(tmp_path)
    conn = sqlite3.connect(db)
    tables = {t: conn.execute(f"SELECT * from {t}").fetchall() for t in ARENA_TABLES}
    cols = {t: [c[1] for c in conn.execute(f"PRAGMA table_info({t})")] for t in ARENA_TABLES}
    assert cols["experiments"][:12] == [
        "id", "name", "totaltime", "timelimit", "memorylimit", "runcount",
        "version", "hostname", "cpuinfo", "date", "seed", "setup",
    ]  # fmt: skip
    assert cols["runs"][:3] == ["id", "experimentid", "plannerid"] and "solved" in cols["runs"]
    assert [row[1] for row in tables["experiments"]] == ["mbm_panda_bookshelf_small", "mbm_panda_cage"]
    # what the runs planned on, their OMPL, seed and time limit: in the table and in the sidecar
    from mpd.provenance import cpu_model

    exp = dict(zip(cols["experiments"], tables["experiments"][0]))
    assert (exp["cpuinfo"], exp["version"], exp["seed"], exp["timelimit"]) == (cpu_model(), "OMPL 2.0.1", "0", 5.0)
    assert exp["grasp_target"] == "obstacle" and "seeds problem_seed" in exp["setup"]
    side = json.loads((tmp_path / mbm_run.SIDECAR).read_text())
    assert (side["cpus"], side["ompl"], side["seed"], side["time_limit_s"]) == ([cpu_model()], ["2.0.1"], 0, 5.0)
    assert side["families"]["cage"] == {
        "problems": 1, "solved": 0, "valid_mpd": 0, "timeout": 0, "invalid_start": 0, "invalid_goal": 1,
    }  # fmt: skip
    # one entry per invocation that planned (one per family here); the rerun found nothing to do and added none
    invocations = mbm_run.read_provenance(tmp_path)
    assert [i["problems"] for i in invocations] == [2, 1]
    assert all(i["cpu"] == cpu_model() and i["ompl"] == "2.0.1" and i["finished"] for i in invocations)
    assert [r["seed"] for r in recs] == [
        problem_seed("mbm", 0, name) for name in ("bookshelf_small/0001", "bookshelf_small/0002", "cage/0001")
    ]
    assert [row[1] for row in tables["plannerConfigs"]] == ["geometric_RRTConnect"]
    assert len(tables["runs"]) == 3 and tables["progress"] == []
    statuses = dict(conn.execute("SELECT value, description FROM enums WHERE name = 'status'").fetchall())
    solved = conn.execute("SELECT problem, solved, status, correct_solution FROM runs ORDER BY id").fetchall()
    assert [(p, s, statuses[st], c) for p, s, st, c in solved] == [
        (1, 1, "Exact solution", 1),
        (2, 1, "Exact solution", 1),
        (1, 0, "Invalid goal", None),
    ]
    conn.close()

    database = pytest.importorskip("plannerarena.database", reason="plannerarena (the dev extra) is not installed")
    data = database.load_database(db)
    assert data["problem_names"] == ["mbm_panda_bookshelf_small", "mbm_panda_cage"]
    assert data["parameters"] == ["family", "grasp target"]
    assert {"time", "solved", "status", "solution length", "correct solution"} <= set(data["attributes"])
    runs = data["runs"]
    assert runs.height == 3 and set(runs["planner"].cast(str).to_list()) == {"RRTConnect"}
    assert runs["solved"].to_list() == [1, 1, 0]


def test_a_goal_beyond_mpds_joint_limits_is_rejected_before_planning(imported):
    """table_pick 31: MBM's URDF allows the goal, mpd's (datasheet) limits do not; the planner's state space holds
    the limits, so planning would only run into its time limit."""
    from mpd.experiments import mbm as mbm_run

    (p,) = [p for p in imported.problems("table_pick") if p.index == 31]
    rec = mbm_run.run_problem(imported, "table_pick", p, mbm_run.BaselineSettings(time_limit=30.0))
    assert (rec["status"], rec["success"], rec["time_first_s"]) == ("invalid_goal", False, None)


def test_rrtconnect_with_the_grasped_object_left_out_plans_a_cage_goal(imported):
    from mpd.experiments import mbm as mbm_run

    (p,) = [p for p in imported.problems("cage") if p.index == 1]
    rec = mbm_run.run_problem(imported, "cage", p, mbm_run.BaselineSettings(time_limit=5.0, grasp_target="ignored"))
    assert (rec["status"], rec["success"], rec["valid_mpd"], rec["left_out"]) == ("ok", True, True, "Cube1")
    with pytest.raises(ValueError, match="grasp_target"):
        mbm_run.BaselineSettings(grasp_target="attached")


def test_database_rejects_what_ompl_cannot_read(tmp_path):
    e = benchmark_db.Experiment("x", 1.0, "OMPL 2.0.1", attributes={"time": "FLOAT"})
    with pytest.raises(ValueError, match="type"):
        benchmark_db.write(tmp_path / "a.db", [e])
    e = benchmark_db.Experiment("x", 1.0, "OMPL 2.0.1", attributes={"time": "REAL"}, runs=[("p", "", {"tim": 1.0})])
    with pytest.raises(ValueError, match="undeclared"):
        benchmark_db.write(tmp_path / "b.db", [e])
    assert not any(tmp_path.iterdir())  # nothing under the final names


def test_cli_import(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from mpd.cli import cli

    monkeypatch.setenv("MPD_CACHE", str(tmp_path))
    res = CliRunner().invoke(cli, ["bench", "mbm", "import", "--families", "cage,bookshelf_small"])
    assert res.exit_code == 0, res.output
    rows = {line.split()[0]: line.split()[1:] for line in res.output.splitlines()[2:]}
    assert rows == {"cage": ["100", "100", "0", "100", "0"], "bookshelf_small": ["100", "100", "100", "0", "0"]}
    res = CliRunner().invoke(cli, ["bench", "mbm", "import", "--families", "cage", "--grasp-target", "ignored"])
    assert res.exit_code == 0, res.output
    assert res.output.splitlines()[2].split() == ["cage", "100", "100", "100", "0", "0"]
    res = CliRunner().invoke(cli, ["bench", "mbm", "import", "--families", "kitchen"])
    assert res.exit_code == 2 and "unknown families" in res.output


@pytest.mark.slow
def test_the_source_package_on_pypi_holds_the_shipped_archive(tmp_path):
    """Downloads vamp-planner's source package (65 MB) with pip; skipped offline."""
    try:
        sdist = mbm.download_sdist(tmp_path)
    except subprocess.CalledProcessError as e:
        pytest.skip(f"pip could not download vamp-planner {mbm.SDIST_VERSION} (offline?): {e.stderr[-300:]!r}")
    assert mbm.archive_sha256(sdist) == mbm.SHIPPED_SHA256
    imp = mbm.import_problems(sdist, families=("cage",), root=tmp_path / "cache")
    assert len(imp.problems("cage")) == 100
