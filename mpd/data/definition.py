"""Dataset definitions: ``datasets/NAME.toml``, read through :func:`mpd.schema.from_dict`.

A definition says what to generate (task, number of contexts, seed), how (planner, validity checker,
clearance, context sampling) and how it is stored and split (chunk size, split fractions). Fields left out
take their defaults; ``None`` means "the task's value" (``clearance`` from ``collision.clearance``,
``time_limit`` from ``data.planner_time_limit``, ``check_step`` by robot, see
:func:`mpd.data.planning.default_check_step`). :func:`resolve` fills them in, and the identity of a dataset is
the hash of the filled definition (without its name and description), the sha256 of the task file and of the
robot file, and :data:`GENERATOR_VERSION`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from mpd.data.planning import PlannerSettings, default_check_step
from mpd.paths import DATASETS_DIR, cache_dir
from mpd.robots.spec import robot_files
from mpd.schema import ConfigError, file_sha256, from_dict, read_toml, stable_hash, to_dict
from mpd.tasks import Task, load_task

# Bump when a change of the generator changes the data of an unchanged definition (part of the identity).
GENERATOR_VERSION = 1


@dataclass(frozen=True)
class CheckerSettings:
    kind: Literal["spheres", "meshes"] = "spheres"
    clearance: float | None = None  # None: the task's collision.clearance
    self_pairs: Literal["sphere_pairs", "all", "none"] = "sphere_pairs"  # PyBullet self-collision link pairs

    def validate(self) -> None:
        if self.clearance is not None and self.clearance < 0:
            raise ValueError("clearance must be >= 0")


@dataclass(frozen=True)
class ContextSettings:
    min_start_goal_distance: float = 0.0  # the authors enforce none during data generation
    max_tries: int = 500  # candidate draws per configuration (the authors' value)

    def validate(self) -> None:
        if self.min_start_goal_distance < 0 or self.max_tries < 1:
            raise ValueError("min_start_goal_distance must be >= 0 and max_tries >= 1")


@dataclass(frozen=True)
class SplitSettings:
    """Fractions of the contexts held out (the rest is training); both directions of a context share one."""

    val: float = 0.025
    test: float = 0.025

    def validate(self) -> None:
        if min(self.val, self.test) < 0 or self.val + self.test >= 1:
            raise ValueError("split fractions must be >= 0 and leave some training data")


@dataclass(frozen=True)
class ProblemSettings:
    """Contexts taken from a benchmark's problems instead of sampled (``[problems]`` of a definition): context i is
    the i mod n-th of the n selected problems, planned in that problem's own scene; a problem's repeats (i // n) are
    planned with their own seeds, so they give different paths. Only ``source = "mbm"`` (the MotionBenchMaker Panda
    problems, :mod:`mpd.data.mbm`) exists: ``families`` (empty: all seven), ``first`` and ``last`` (the problem
    indices kept, 1 to 100, inclusive), and how the scene is read (``grasp_target``, ``cylinder_slabs``)."""

    source: Literal["mbm"] = "mbm"
    families: tuple[str, ...] = ()
    first: int = 1
    last: int = 50
    grasp_target: Literal["obstacle", "ignored"] = "ignored"
    cylinder_slabs: int = 4

    def validate(self) -> None:
        from mpd.data.mbm import FAMILIES

        bad = [f for f in self.families if f not in FAMILIES]
        if bad:
            raise ValueError(f"families: unknown {bad[0]!r} (one of {', '.join(FAMILIES)})")
        if not 1 <= self.first <= self.last <= 100:
            raise ValueError(f"first and last must satisfy 1 <= first <= last <= 100, got {self.first}, {self.last}")
        if self.cylinder_slabs < 1:
            raise ValueError("cylinder_slabs must be >= 1")


@dataclass(frozen=True)
class DatasetDefinition:
    name: str
    task: str  # task name or path to a task file
    n_contexts: int
    seed: int = 0
    chunk_size: int = 100
    description: str = ""
    planner: PlannerSettings = field(default_factory=PlannerSettings)
    checker: CheckerSettings = field(default_factory=CheckerSettings)
    contexts: ContextSettings = field(default_factory=ContextSettings)
    split: SplitSettings = field(default_factory=SplitSettings)
    problems: ProblemSettings | None = None  # contexts from a benchmark's problems (None: sampled from the task)

    def validate(self) -> None:
        if self.n_contexts < 1:
            raise ConfigError(None, "n_contexts", f"must be positive, got {self.n_contexts}")
        if self.chunk_size < 1:
            raise ConfigError(None, "chunk_size", f"must be positive, got {self.chunk_size}")
        if self.seed < 0:
            raise ConfigError(None, "seed", f"must be >= 0, got {self.seed}")

    @property
    def n_chunks(self) -> int:
        return -(-self.n_contexts // self.chunk_size)

    def chunk_range(self, i: int) -> tuple[int, int]:
        return i * self.chunk_size, min((i + 1) * self.chunk_size, self.n_contexts)


# PlannerSettings leaves time_limit and check_step to the task when a definition does not give them
@dataclass(frozen=True)
class _PlannerFields(PlannerSettings):
    time_limit: float | None = None  # type: ignore[assignment]
    check_step: float | None = None  # type: ignore[assignment]

    def validate(self) -> None:
        if self.time_limit is not None and self.time_limit <= 0:
            raise ValueError("time_limit must be positive")
        if self.check_step is not None and self.check_step <= 0:
            raise ValueError("check_step must be positive")
        self.validate_fixed_fields()


@dataclass(frozen=True)
class _DefinitionFile(DatasetDefinition):
    planner: _PlannerFields = field(default_factory=_PlannerFields)  # type: ignore[assignment]


@dataclass(frozen=True)
class ResolvedDefinition:
    """A definition with every default filled in, its task, where it came from and its identity."""

    definition: DatasetDefinition
    task: Task
    path: Path | None
    identity: str

    def __reduce__(self):
        # workers rebuild the task from its file instead of unpickling torch state
        return (_rebuild, (self.definition, str(self.task.path), self.path, self.identity))

    @property
    def name(self) -> str:
        return self.definition.name

    @property
    def clearance(self) -> float:
        return float(self.definition.checker.clearance)

    @property
    def data_dir(self) -> Path:
        return cache_dir() / "datasets" / f"{self.name}-{self.identity}"

    @property
    def lock_path(self) -> Path:
        base = self.path.parent if self.path is not None else DATASETS_DIR
        return base / f"{self.name}.lock.json"


def _rebuild(defn: DatasetDefinition, task_path: str, path: Path | None, identity: str) -> ResolvedDefinition:
    return ResolvedDefinition(defn, load_task(task_path), path, identity)


def resolve_definition_path(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise ConfigError(p, "", "file not found")
        return p
    q = DATASETS_DIR / f"{name_or_path}.toml"
    if not q.exists():
        known = ", ".join(sorted(x.stem for x in DATASETS_DIR.glob("*.toml"))) or "none"
        raise ConfigError(name_or_path, "", f"unknown dataset (known: {known}; or give a path to a .toml file)")
    return q


def robot_file(task: Task) -> Path:
    """The robot description file of a task (its sphere model and limits shape the data too)."""
    name = task.spec.robot.name
    return robot_files().get(name, Path(name))


# the sections of a task file that shape its data; cost weights, inference and training settings do not, so
# tuning them does not invalidate (and regenerate) the datasets
DATA_SECTIONS = ("schema_version", "environment", "robot", "context", "trajectory", "collision", "data")


def task_data_hash(task: Task) -> str:
    """Hash of the data-relevant sections of a task file (after parsing, so comments and layout do not count)."""
    spec = to_dict(task.spec)
    return stable_hash({k: spec[k] for k in DATA_SECTIONS}, n=64)


def identity_of(defn: DatasetDefinition, task: Task) -> str:
    """Hash of the filled definition (name and description aside), the data-relevant sections of the task file
    (``DATA_SECTIONS``), the robot file and GENERATOR_VERSION."""
    content = {k: v for k, v in to_dict(defn).items() if k not in ("name", "description")}
    if content["planner"].get("resample") == "v1":
        # the definitions generated before planner.resample existed keep their identities (and their data)
        del content["planner"]["resample"]
    if content["planner"].get("max_checks") == 0:
        # the definitions without a check budget keep their identities (and their data)
        del content["planner"]["max_checks"]
    if content.get("problems") is None:
        # the definitions of sampled contexts keep their identities (and their data)
        content.pop("problems", None)
    else:
        from mpd.data.mbm import FORMAT_VERSION, SHIPPED_SHA256

        # the problems' source enters the identity: the archive and the importer's format
        content["problems"]["archive_sha256"] = SHIPPED_SHA256
        content["problems"]["format"] = FORMAT_VERSION
    return stable_hash(content, task_data_hash(task), file_sha256(robot_file(task)), GENERATOR_VERSION)


def resolve(raw: DatasetDefinition, path: Path | None = None) -> ResolvedDefinition:
    """Fill the task-dependent defaults and compute the identity."""
    src = path if path is not None else "<definition>"
    task_ref: str | Path = raw.task
    if path is not None and not Path(raw.task).is_absolute() and (Path(path).parent / raw.task).is_file():
        task_ref = Path(path).parent / raw.task  # a task file next to the definition (`mpd tasks new`)
    try:
        task = load_task(task_ref)
    except ConfigError as e:
        raise ConfigError(src, "task", e.detail) from None
    p = raw.planner
    planner = PlannerSettings(
        name=p.name,
        time_limit=task.spec.data.planner_time_limit if p.time_limit is None else p.time_limit,
        range=p.range,
        check_step=default_check_step(task) if p.check_step is None else p.check_step,
        simplify=p.simplify,
        resample=p.resample,
        max_checks=p.max_checks,
    )
    clearance = task.spec.collision.clearance if raw.checker.clearance is None else raw.checker.clearance
    fields = {f.name: getattr(raw, f.name) for f in dataclasses.fields(DatasetDefinition)}
    fields["task"] = task.name  # the task file itself enters the identity through its sha256
    fields["planner"] = planner
    fields["checker"] = dataclasses.replace(raw.checker, clearance=float(clearance))
    defn = DatasetDefinition(**fields)
    return ResolvedDefinition(defn, task, path, identity_of(defn, task))


def load_definition(name_or_path: str | Path) -> ResolvedDefinition:
    """Read ``datasets/NAME.toml`` (or a path); errors name the file and the field."""
    path = resolve_definition_path(name_or_path)
    raw = from_dict(_DefinitionFile, read_toml(path), source=path)
    if raw.name != path.stem:
        raise ConfigError(
            path,
            "name",
            f"{raw.name!r} differs from the file name {path.stem!r} (the lock file is named after the definition)",
        )
    return resolve(raw, path)
