"""Every planner setting has a type and a valid range, checked wherever settings are built (the command line, a
spec axis, a task file) with one line naming the setting, the value and what is allowed.

The examples below are written by hand from what each setting means (not read from mpd.planners.validation), so
a range changed by mistake fails here; a new field without examples fails ``test_every_field_has_examples``."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
from tiny import write_spec_file

from mpd.experiments.spec import load_spec
from mpd.planners import PlannerSettings, planner_settings
from mpd.planners.validation import check_setting, parse_assignments
from mpd.schema import ConfigError
from mpd.tasks import load_task, task_files

TASK = "EnvSimple2D-RobotPointMass2D"
REPO = Path(__file__).resolve().parents[1]

# field: (values that must be accepted, values that must be rejected)
EXAMPLES: dict[str, tuple[list, list]] = {
    "preset": (["official", "paper"], ["offical", 1]),
    "sampler": (["ddim", "ddpm"], ["ddip", None]),
    "ddim_steps": ([1, 15], [0, -3, 2.5, "15"]),
    "network_precision": (["fp32", "bf16", "auto"], ["fp16", 1]),
    "network_compile": ([True, False], ["yes", 1, None]),
    "ddim_schedule": (["quadratic", "uniform"], ["linear"]),
    "ddim_variant": (["official", "paper"], ["x"]),
    "eta": ([0, 0.5, 1.0], [-0.1, 1.1, "abc"]),
    "ddpm_variance_scale": ([0.0, 0.49, 1.0], [-0.01, 1.5]),
    "guide_fraction": ([0.0, 0.3, 1.0, None], [-0.1, 1.01, "abc"]),
    "n_guided_steps": ([0, 3], [-1, 1.5]),
    "n_inner_steps": ([1, 4], [0, -1, 2.0]),
    "prior_weight": ([0.0, 0.25, 2.0], [-0.25]),
    "guide_lr": ([1e-6, 1, 1.0], [0, -1, "abc", float("nan"), float("inf")]),
    "max_perturb": ([0.01, 0.15], [0, -0.15]),
    "grad_clip": ([None, 0.5, 1], [0, -1]),
    "guided_update": (["official", "paper"], ["both"]),
    "ddpm_guide_fraction": ([0.0, 0.2, 1.0], [1.5, -0.2, None]),
    "ddpm_prior_weight": ([0.0, 0.95], [-0.95]),
    "ddpm_n_inner_steps": ([1, 2], [0]),
    "ddpm_guide_lr": ([0.01], [0, -0.01]),
    "opt_steps": ([0, 12], [-1, 1.5]),
    "opt_lr": ([0.01, 1.0], [0, -0.01]),
    "opt_max_perturb": ([0.15], [0]),
    "opt_grad_clip": ([None, 1.0], [0]),
    "cost_preset": (["official", "paper"], ["x"]),
    "sdf_mode": (["nearest", "trilinear", "analytic"], ["cubic"]),
    "gp_prior": (["authors", "bridge"], ["sklearn", None]),
    "gp_sigma": ([0.3], [0, -0.3]),
    "gp_lengthscale": ([0.25], [0]),
    "rrt_time_limit": ([0.5, 10], [0, -1]),
    "ik_restarts": ([1, 4], [0, 1.5]),
}
FIELDS = [f.name for f in dataclasses.fields(PlannerSettings)]


def test_every_field_has_examples():
    assert sorted(EXAMPLES) == sorted(FIELDS)


def test_the_defaults_and_the_presets_are_valid():
    task = load_task(TASK)
    for preset in ("official", "paper"):
        s = planner_settings(task, preset)
        for f in FIELDS:
            check_setting(f, getattr(s, f))


@pytest.mark.parametrize("name", FIELDS)
def test_each_setting_accepts_and_rejects(name):
    good, bad = EXAMPLES[name]
    for v in good:
        check_setting(name, v, "--set")
        assert getattr(PlannerSettings().replace(**{name: v}), name) == v
    for v in bad:
        with pytest.raises(ConfigError) as e:
            check_setting(name, v, "--set")
        msg = str(e.value)
        assert msg.startswith(f"--set: {name}: ") and repr(v) in msg and "\n" not in msg
        with pytest.raises(ConfigError):  # the settings object itself cannot be built with it either
            PlannerSettings().replace(**{name: v})


def test_assignments_from_the_command_line():
    assert parse_assignments(["guide_lr=0.5", "grad_clip=null", "sampler=ddpm"]) == {
        "guide_lr": 0.5,
        "grad_clip": None,
        "sampler": "ddpm",
    }
    with pytest.raises(ConfigError, match=r"^--set: nosuch: unknown planner setting \(allowed: preset, "):
        parse_assignments(["nosuch=1"])
    with pytest.raises(ConfigError, match="expected NAME=VALUE"):
        parse_assignments(["guide_lr"])


@pytest.mark.parametrize(
    ("item", "expect"),
    [
        ("guide_lr=abc", "--set: guide_lr: expected a number, got str 'abc'"),
        ("guide_lr=-1", "--set: guide_lr: -1 is not allowed (allowed: a number > 0"),
        ("nosuch=1", "--set: nosuch: unknown planner setting"),
    ],
)
def test_mpd_plan_rejects_a_setting_in_one_line_before_loading_a_model(tmp_path, item, expect):
    # an empty cache: had the settings been checked after the model lookup, the error would be "no trained model"
    env = {"MPD_CACHE": str(tmp_path / "cache"), "PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}
    cmd = [sys.executable, "-m", "mpd.cli", "plan", "--task", TASK, "--planner", "mpd", "--out", str(tmp_path)]
    r = subprocess.run([*cmd, "--set", item], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith(f"error: {expect}") and r.stderr.strip().count("\n") == 0, r.stderr


def _spec(tmp_path: Path, axis_line: str, task: str = TASK) -> Path:
    axes = {"task": [task], "method": ["mpd"]}
    return write_spec_file(tmp_path / "s.toml", axes, {task: {"dataset": "x"}}, after_axes=axis_line, name="s")


@pytest.mark.parametrize(
    ("line", "where"),
    [
        ('"planner.guide_lr" = [0.5, -1]', "axes.planner.guide_lr: -1 is not allowed"),
        ('"planner.guide_lr" = ["abc"]', "axes.planner.guide_lr: expected a number"),
        ('"planner.ddim_steps" = [0]', "axes.planner.ddim_steps: 0 is not allowed"),
        ('"planner.eta" = [1.5]', "axes.planner.eta: 1.5 is not allowed"),
    ],
)
def test_spec_axes_get_the_same_checks(tmp_path, line, where):
    p = _spec(tmp_path, line)
    with pytest.raises(ConfigError) as e:
        load_spec(p)
    assert str(e.value).startswith(f"{p}: {where}")


def test_task_file_settings_are_checked_when_a_spec_loads(tmp_path):
    text = task_files()[TASK].read_text()
    assert "guide_fraction = 0.3" in text
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("guide_fraction = 0.3", "guide_fraction = 1.5"))
    with pytest.raises(ConfigError) as e:
        load_spec(_spec(tmp_path, "", task=str(bad)))
    assert str(e.value).startswith(f"{bad.resolve()}: inference.guide_fraction: 1.5 is not allowed")
