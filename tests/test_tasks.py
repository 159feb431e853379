"""Task files: loading by name and path, the ``mpd tasks`` verbs, one-line errors, user files, rotation."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TASKS

from mpd.cli import cli
from mpd.cli.tasks import tasks
from mpd.envs import rot_z
from mpd.schema import ConfigError
from mpd.tasks import list_tasks, load_task, task_files

SIMPLE = "EnvSimple2D-RobotPointMass2D"


def test_six_tasks_by_name_and_path():
    assert sorted(list_tasks()) == sorted(TASKS)
    for name in TASKS:
        t = load_task(name)
        assert t.name == name and t.path.stem == name
        by_path = load_task(str(task_files()[name]))
        assert by_path.spec == t.spec
    t = load_task("EnvWarehouse-RobotPanda")
    assert (t.dof, t.dim, t.ee_goal, t.robot.name) == (7, 3, True, "RobotPanda")


def test_unknown_task_name():
    with pytest.raises(ConfigError, match="unknown task"):
        load_task("EnvNoSuchTask")


# ------------------------------------------------------------------------------------------------- CLI
def test_cli_list():
    r = CliRunner().invoke(cli, ["tasks", "list"])
    assert r.exit_code == 0, r.output
    lines = r.output.strip().splitlines()
    assert lines[0].split() == ["task", "robot", "context", "dof"]
    rows = {ln.split()[0]: ln.split()[1:] for ln in lines[1:]}
    assert set(rows) == set(TASKS)
    assert rows["EnvPlanar4Link-RobotPlanar4Link"] == ["RobotPlanar4Link", "goal_ee_pose", "4"]
    assert rows[SIMPLE] == ["RobotPointMass2D", "goal_joint_position", "2"]


@pytest.mark.parametrize("name", [SIMPLE, "EnvPlanar4Link-RobotPlanar4Link"])
def test_cli_check_prints_summary_and_fractions(name):
    r = CliRunner().invoke(tasks, ["check", str(task_files()[name]), "--samples", "4000"])
    assert r.exit_code == 0, r.output
    assert ": ok" in r.output and name in r.output
    fractions = re.findall(r"^\s+(training scene|extra objects)\s+(\w+)\s+([0-9.]+)$", r.output, re.M)
    kinds = {"inside", "dilated"} if "PointMass" in name else {"env", "self", "either"}
    assert {(s, k) for s, k, _ in fractions} == {(s, k) for s in ("training scene", "extra objects") for k in kinds}
    assert all(0 <= float(v) <= 1 for *_, v in fractions)


def test_cli_show_writes_a_figure(tmp_path):
    out = tmp_path / "fig" / "planar.png"
    r = CliRunner().invoke(
        tasks,
        [
            "show",
            "EnvPlanar2Link-RobotPlanar2Link",
            "--extra-objects",
            "--rotation",
            "20",
            "--seed",
            "3",
            "--out",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    q = torch.tensor([float(v) for v in re.search(r"q = \[(.*)\]", r.output).group(1).split(",")], dtype=torch.float64)
    # the drawn configuration is valid in the scene that was drawn (rounded to 4 decimals in the message)
    from mpd.collision import CollisionChecker

    assert CollisionChecker(load_task("EnvPlanar2Link-RobotPlanar2Link"), True, 20.0).configs(q).valid


def test_show_is_seeded():
    from mpd.cli.tasks import random_valid_configuration

    t = load_task(SIMPLE)
    a = random_valid_configuration(t, seed=5)
    assert torch.equal(a, random_valid_configuration(t, seed=5))
    assert not torch.equal(a, random_valid_configuration(t, seed=6))


# ------------------------------------------------------------------------------------------- bad files
def _variant(tmp_path: Path, old: str, new: str, count: int = 1) -> Path:
    text = task_files()[SIMPLE].read_text()
    assert text.count(old) >= count, old
    p = tmp_path / "bad-task.toml"
    p.write_text(text.replace(old, new, count))
    return p


BAD = [
    # (what, old text, new text, field in the message, words in the message)
    ("typo key", "n_control_points = ", "n_control_pionts = ", "trajectory.n_control_pionts", "unknown key"),
    ("wrong type", "duration = 10.0", 'duration = "ten"', "trajectory.duration", "expected a number"),
    ("missing field", "duration = 10.0\n", "", "trajectory.duration", "missing required field"),
    (
        "negative radius",
        "radius = 0.125",
        "radius = -0.125",
        "environment.obstacles[0].radius",
        "positive radius",
    ),
    (
        "workspace low > high",
        "workspace = [[-1.0, -1.0], [1.0, 1.0]]",
        "workspace = [[1.0, -1.0], [-1.0, 1.0]]",
        "environment.workspace",
        "low < high",
    ),
    (
        "unknown robot",
        'name = "RobotPointMass2D"',
        'name = "RobotPointMass3D"',
        "robot.name",
        "unknown robot",
    ),
    ("bad literal", 'kind = "goal_joint_position"', 'kind = "goal_joint"', "context.kind", "is not one of"),
    (
        "network of no profile",
        "[training.cpu]",
        "[model_profiles.laptop]\nunet_dim = 16\n\n[training.cpu]",
        "model_profiles.laptop",
        "no training profile 'laptop'",
    ),
    (
        "network size zero",
        "[training.cpu]",
        "[model_profiles.cpu]\nunet_dim_mults = [1, 0]\n\n[training.cpu]",
        "model_profiles.cpu.unet_dim_mults",
        "must be positive",
    ),
    (
        "network typo",
        "[training.cpu]",
        "[model_profiles.cpu]\nunet_dims = 16\n\n[training.cpu]",
        "model_profiles.cpu.unet_dims",
        "unknown key",
    ),
]


@pytest.mark.parametrize("what, old, new, field, words", BAD, ids=[b[0] for b in BAD])
def test_bad_file_is_one_clear_line(tmp_path, what, old, new, field, words):
    p = _variant(tmp_path, old, new)
    with pytest.raises(ConfigError) as e:
        load_task(p)
    msg = str(e.value)
    assert msg.startswith(f"{p.resolve()}: {field}: ") or msg.startswith(f"{p}: {field}: "), msg
    assert words in msg and "\n" not in msg
    r = CliRunner().invoke(tasks, ["check", str(p)])
    assert r.exit_code == 2
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1 and str(p.name) in err and field in err and words in err, err
    assert "Traceback" not in r.output


def test_invalid_toml_and_missing_file(tmp_path):
    p = _variant(tmp_path, "[trajectory]", "[trajectory")
    r = CliRunner().invoke(tasks, ["check", str(p)])
    assert r.exit_code == 2 and "invalid TOML" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = CliRunner().invoke(tasks, ["show", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "x.png")])
    assert r.exit_code == 2 and "file not found" in r.stderr


USER_TASK = """
schema_version = 1
name = "MyCorridor-RobotPointMass2D"
description = "two walls and a ball, written by a user"

[environment]
dim = 2
workspace = [[-1.0, -1.0], [1.0, 1.0]]
[[environment.obstacles]]
type = "box"
centre = [0.0, 0.6]
size = [0.2, 0.8]
[[environment.obstacles]]
type = "box"
centre = [0.0, -0.6]
size = [0.2, 0.8]
[[environment.extra_objects]]
type = "sphere"
centre = [0.5, 0.0]
radius = 0.15

[robot]
name = "RobotPointMass2D"

[context]
kind = "goal_joint_position"

[trajectory]
duration = 5.0
n_control_points = 16

[collision]
cost_margin = 0.02

[costs.weights]
collision = 1.0
"""


def test_user_task_file_loads_without_code_change(tmp_path):
    p = tmp_path / "my_task.toml"
    p.write_text(USER_TASK)
    t = load_task(p)
    assert t.name == "MyCorridor-RobotPointMass2D" and t.path == p.resolve()
    env, extra = t.env(), t.env(extra_objects=True)
    x = torch.tensor([[0.0, 0.6], [0.0, 0.0], [0.5, 0.0]], dtype=torch.float64)
    assert env.sdf(x).tolist() == pytest.approx([-0.1, 0.2, np.hypot(0.4, 0.2)])  # wall, gap, wall corner
    assert extra.sdf(x)[2].item() == pytest.approx(-0.15)
    from mpd.collision import CollisionChecker
    from mpd.trajectory import make_parametrization

    assert CollisionChecker(t).configs(x).valid.tolist() == [False, True, True]
    assert make_parametrization(t).n_params == 16
    r = CliRunner().invoke(tasks, ["check", str(p), "--samples", "20000"])
    assert r.exit_code == 0, r.output
    # two walls of 0.2 x 0.8 in a 2 x 2 square: 8 % of the workspace
    inside = float(re.search(r"training scene\s+inside\s+([0-9.]+)", r.output).group(1))
    assert inside == pytest.approx(0.08, abs=0.01)


# -------------------------------------------------------------------------------------------- rotation
@pytest.mark.parametrize(
    "name", [SIMPLE, "EnvPlanar4Link-RobotPlanar4Link", "EnvWarehouse-RobotPanda", "EnvSpheres3D-RobotPanda"]
)
@pytest.mark.parametrize("extra", [False, True])
def test_rotated_scene_is_the_scene_rotated(name, extra):
    """sdf_rotated(R x) = sdf(x) for the rotation R about z, with rotated boxes (Warehouse table) included."""
    t = load_task(name)
    g = torch.Generator().manual_seed(0)
    lo, hi = (torch.as_tensor(v) for v in t.env().workspace)
    x = lo + torch.rand(5000, t.dim, generator=g, dtype=torch.float64) * (hi - lo)
    for deg in (30.0, -75.0, 180.0):
        R = torch.as_tensor(rot_z(deg, t.dim))
        d0, g0 = t.env(extra).sdf(x, grad=True)
        d1, g1 = t.env(extra, deg).sdf(x @ R.T, grad=True)
        torch.testing.assert_close(d1, d0, rtol=0, atol=1e-12)
        torch.testing.assert_close(g1, g0 @ R.T, rtol=0, atol=1e-9)
    assert np.isclose(t.env(extra, 30.0).rotation_deg, 30.0)


def test_a_profile_network_changes_only_its_fields_and_only_its_models(tmp_path):
    """``[model_profiles.cpu]``: the cpu profile's network is [model] with the given sizes; other profiles and a task
    without the table keep [model] (and so their models' identities)."""
    from mpd.experiments.artifacts import model_settings

    base = load_task(SIMPLE)
    p = _variant(tmp_path, "[training.cpu]", "[model_profiles.cpu]\nunet_dim = 16\ncontext_dim = 8\n\n[training.cpu]")
    t = load_task(p)
    assert t.model("cpu") == dataclasses.replace(base.spec.model, unet_dim=16, context_dim=8)
    assert t.model("paper") == t.model() == base.spec.model == base.model("cpu")
    # a spec's model.* value applies on top of the profile's network
    got = model_settings(t, (("model.unet_dim", 24),), "cpu")
    assert (got.unet_dim, got.context_dim, got.unet_dim_mults) == (24, 8, base.spec.model.unet_dim_mults)
