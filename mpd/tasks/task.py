"""Loading a task file into a :class:`Task`: environment, robot, context kind, trajectory and cost settings."""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

from mpd.envs import Environment
from mpd.robots import Robot, get_robot
from mpd.schema import ConfigError, file_sha256, from_dict, read_toml
from mpd.tasks.spec import CostWeights, ModelSpec, TaskSpec, TrainingSpec

DATA_DIR = Path(__file__).parent / "data"


class Task:
    """A benchmark task: one TOML file. Immutable; environments are built on demand and cached."""

    def __init__(self, spec: TaskSpec, path: Path):
        self.spec = spec
        self.path = Path(path)
        self.name = spec.name
        self.file_hash = file_sha256(self.path)
        try:
            self.robot: Robot = get_robot(spec.robot.name)
        except ConfigError as e:
            raise ConfigError(self.path, "robot.name", e.detail) from None
        if self.robot.task_dim != spec.environment.dim:
            raise ConfigError(
                self.path,
                "robot.name",
                f"{self.robot.name} moves in {self.robot.task_dim}-D, the environment is {spec.environment.dim}-D",
            )
        self._envs: dict[tuple[bool, float], Environment] = {}

    def __repr__(self) -> str:
        return f"Task({self.name!r}, robot={self.robot.name}, context={self.spec.context.kind})"

    # -- shortcuts ---------------------------------------------------------------------------------------
    @property
    def dof(self) -> int:
        return self.robot.dof

    @property
    def ee_goal(self) -> bool:
        """True when the context holds an end-effector goal pose instead of a goal configuration."""
        return self.spec.context.kind == "goal_ee_pose"

    @property
    def dim(self) -> int:
        return self.spec.environment.dim

    def env(self, extra_objects: bool = False, rotation_deg: float = 0.0) -> Environment:
        key = (bool(extra_objects), float(rotation_deg))
        if key not in self._envs:
            self._envs[key] = Environment(self.spec.environment, *key)
        return self._envs[key]

    def cost_weights(self, preset: str = "official") -> CostWeights:
        if preset == "official":
            return self.spec.costs.weights
        if preset == "paper":
            if self.spec.costs.paper_weights is None:
                raise ConfigError(self.path, "costs.paper_weights", "missing (needed by the 'paper' preset)")
            return self.spec.costs.paper_weights
        raise ValueError(f"unknown cost preset {preset!r} (official, paper)")

    def model(self, profile: str | None = None) -> ModelSpec:
        """The network of a training profile: the task's ``[model]`` (the paper's sizes) with the profile's
        ``[model_profiles.<profile>]`` changes, if any."""
        override = self.spec.model_profiles.get(profile) if profile is not None else None
        return dataclasses.replace(self.spec.model, **override.changes()) if override else self.spec.model

    def training(self, profile: str) -> TrainingSpec:
        if profile not in self.spec.training:
            raise ConfigError(
                self.path,
                f"training.{profile}",
                f"no such training profile (this task has: {', '.join(self.spec.training)})",
            )
        return self.spec.training[profile]


def task_files() -> dict[str, Path]:
    return {p.stem: p for p in sorted(DATA_DIR.glob("*.toml"))}


def list_tasks() -> list[str]:
    return list(task_files())


def resolve_task_path(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise ConfigError(p, "", "file not found")
        return p
    files = task_files()
    if str(name_or_path) not in files:
        raise ConfigError(name_or_path, "", f"unknown task (known: {', '.join(files)}; or give a path to a .toml file)")
    return files[str(name_or_path)]


@functools.lru_cache(maxsize=32)
def _load(path: str, mtime_ns: int) -> Task:
    p = Path(path)
    return Task(from_dict(TaskSpec, read_toml(p), source=p), p)


def load_task(name_or_path: str | Path) -> Task:
    """Load a task by name (``EnvSimple2D-RobotPointMass2D``) or by path to a TOML file."""
    p = resolve_task_path(name_or_path).resolve()
    return _load(str(p), p.stat().st_mtime_ns)
