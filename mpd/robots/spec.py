"""Robot description files (``mpd/robots/data/*.toml``): schema and loading."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from mpd.schema import ConfigError, from_dict, read_toml

DATA_DIR = Path(__file__).parent / "data"


@dataclass(frozen=True)
class JointSpec:
    name: str
    type: Literal["revolute", "prismatic", "fixed"]
    parent: str
    child: str
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class UrdfSpec:
    path: str  # "pybullet_data:<relative path>" or a filesystem path
    end_link: str
    fixed_joints: dict[str, float] = field(default_factory=dict)

    def resolve(self) -> Path:
        if self.path.startswith("pybullet_data:"):
            import pybullet_data

            return Path(pybullet_data.getDataPath()) / self.path.split(":", 1)[1]
        return Path(os.path.expanduser(self.path))


@dataclass(frozen=True)
class LimitsSpec:
    position: list[tuple[float, float]]
    velocity: list[float] | None = None
    acceleration: list[float] | None = None


@dataclass(frozen=True)
class SphereSpec:
    link: str
    centre: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class SelfCollisionSpec:
    link_pairs: list[tuple[str, str]] = field(default_factory=list)


@dataclass(frozen=True)
class ShapeSpec:
    link: str
    shape: Literal["sphere", "cylinder", "box"]
    radius: float = 0.0
    length: float = 0.0
    size: tuple[float, float, float] = (0.0, 0.0, 0.0)
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PybulletSpec:
    """How the robot is built in PyBullet for exact (mesh / primitive) collision checking."""

    source: Literal["urdf", "shapes"]
    shapes: list[ShapeSpec] = field(default_factory=list)


@dataclass(frozen=True)
class RobotSpec:
    name: str
    task_dim: Literal[2, 3]
    ee_link: str
    limits: LimitsSpec
    spheres: list[SphereSpec]
    pybullet: PybulletSpec
    joints: list[JointSpec] = field(default_factory=list)
    urdf: UrdfSpec | None = None
    self_collision: SelfCollisionSpec = field(default_factory=SelfCollisionSpec)

    def validate(self) -> None:
        if (self.urdf is None) == (not self.joints):
            raise ValueError("give exactly one of [urdf] or [[joints]]")
        dof = sum(j.type != "fixed" for j in self.joints) if self.joints else len(self.limits.position)
        if len(self.limits.position) != dof:
            raise ConfigError(
                None,
                "limits.position",
                f"expected {dof} [lower, upper] pairs, got {len(self.limits.position)}",
            )
        for i, (lo, hi) in enumerate(self.limits.position):
            if not lo < hi:
                raise ValueError(f"limits.position[{i}]: lower {lo} is not below upper {hi}")
        for key in ("velocity", "acceleration"):
            v = getattr(self.limits, key)
            if v is not None and (len(v) != dof or min(v) <= 0):
                raise ValueError(f"limits.{key}: expected {dof} positive numbers, got {v}")
        if not self.spheres:
            raise ValueError("spheres: at least one collision sphere is needed")


def robot_files() -> dict[str, Path]:
    return {p.stem: p for p in sorted(DATA_DIR.glob("*.toml"))}


def load_robot_spec(name_or_path: str | Path) -> RobotSpec:
    p = Path(name_or_path)
    if not p.suffix:
        files = robot_files()
        if str(name_or_path) not in files:
            raise ConfigError(name_or_path, "", f"unknown robot (known: {', '.join(files)})")
        p = files[str(name_or_path)]
    return from_dict(RobotSpec, read_toml(p), source=p)
