"""Experiment specs (``benchmarks/specs/*.toml``): schema, validation and expansion into cells.

A spec names the tasks, the methods and the ablation axes; the runner takes their Cartesian product, drops the
combinations matched by ``[[exclude]]`` (and, from the command line, keeps only those matching ``--only``), and
runs every remaining *cell* on the same evaluation contexts. Example::

    name = "quick"
    n_contexts = 10
    n_samples = 100
    seeds = [0]

    [axes]
    task = ["EnvSimple2D-RobotPointMass2D"]
    method = ["mpd", "dprior", "gp-cost"]
    extra_objects = [false, true]
    "planner.guide_lr" = [0.5, 1.0]        # any planner setting is an axis

    [[exclude]]
    method = "gp-cost"
    extra_objects = false

    [tasks."EnvSimple2D-RobotPointMass2D"]
    dataset = "EnvSimple2D-RobotPointMass2D-small"
    profile = "cpu"
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mpd.planners.settings import PRESETS, PlannerSettings
from mpd.schema import ConfigError, from_dict, read_toml, stable_hash
from mpd.trajectory import PARAMETRIZATIONS

SPEC_DIR = Path(__file__).resolve().parents[2] / "benchmarks" / "specs"

# every axis with its allowed values (None: any value of the right type)
AXES: dict[str, tuple | None] = {
    "task": None,
    "method": None,
    "parametrization": PARAMETRIZATIONS,
    "preset": PRESETS,
    "sampler": ("ddim", "ddpm"),
    "extra_objects": (False, True),
    "rotation_deg": None,
    "n_samples": None,
    "seed": None,
}
DEFAULTS: dict[str, Any] = {
    "parametrization": "bspline",
    "preset": "official",
    "sampler": "ddim",
    "extra_objects": False,
    "rotation_deg": 0.0,
}
PLANNER_PREFIX = "planner."


@dataclass(frozen=True)
class TaskSettings:
    """Which dataset and which training profile a task uses in this spec."""

    dataset: str
    profile: str = "cpu"
    train_steps: int | None = None  # override the profile's step count (e.g. a short demo training)
    n_contexts: int | None = None  # override the spec's number of evaluation contexts for this task
    # where the evaluation contexts come from (mpd.data.eval_contexts): "held-out" (the dataset's held-out paths,
    # as the authors; the default) or "sampled" (mpd's earlier dataset-independent contexts)
    contexts: str = "held-out"


@dataclass(frozen=True)
class SpecFile:
    name: str
    axes: dict[str, list[Any]]
    tasks: dict[str, TaskSettings]
    description: str = ""
    n_contexts: int = 100
    n_samples: int = 100
    seeds: list[int] = field(default_factory=lambda: [0])
    exclude: list[dict[str, Any]] = field(default_factory=list)
    record_contexts: int = 1  # contexts per cell streamed to the Rerun recording (with every denoising step)
    # picks the evaluation contexts (their order in the held-out split); the seeds axis is the sampling noise only
    context_seed: int = 0
    device: str = "auto"


@dataclass(frozen=True)
class Cell:
    """One combination of axis values. ``params`` holds every axis (collapsed axes are None)."""

    params: tuple[tuple[str, Any], ...]

    @property
    def p(self) -> dict[str, Any]:
        return dict(self.params)

    @property
    def key(self) -> str:
        return stable_hash(self.p, n=12)

    def planner_overrides(self) -> dict[str, Any]:
        return {k[len(PLANNER_PREFIX) :]: v for k, v in self.params if k.startswith(PLANNER_PREFIX) and v is not None}

    def label(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self.params if v is not None)


class Spec:
    def __init__(self, data: SpecFile, path: Path | None, raw: dict):
        self.data = data
        self.path = path
        self.raw = raw
        self.name = data.name
        self.hash = stable_hash(raw, n=12)

    def __repr__(self) -> str:
        return f"Spec({self.name!r}, {len(self.cells())} cells, hash {self.hash})"

    def cells(self, only: dict[str, list[Any]] | None = None) -> list[Cell]:
        """The matrix: Cartesian product of the axes, minus excludes, restricted by ``only``, with axes that a method
        does not use collapsed to None (so e.g. `sampler` does not multiply GPprior+Cost cells)."""
        from mpd.planners import PLANNERS

        axes = dict(self.data.axes)
        for k, v in DEFAULTS.items():
            axes.setdefault(k, [v])
        axes.setdefault("n_samples", [self.data.n_samples])
        axes.setdefault("seed", list(self.data.seeds))
        names = list(axes)
        seen, out = set(), []
        for combo in itertools.product(*(axes[n] for n in names)):
            p = dict(zip(names, combo))
            if any(all(_match(p.get(k), v) for k, v in ex.items()) for ex in self.data.exclude):
                continue
            if only and not all(any(_match(p.get(k), v) for v in vals) for k, vals in only.items()):
                continue
            planner = PLANNERS[p["method"]]
            for a in planner.unused_axes:
                if a in p:
                    p[a] = None
            cell = Cell(tuple(sorted(p.items())))
            if cell.params not in seen:
                seen.add(cell.params)
                out.append(cell)
        return out


def _match(value: Any, pattern: Any) -> bool:
    if isinstance(pattern, list):
        return any(_match(value, x) for x in pattern)
    if isinstance(value, bool) or isinstance(pattern, bool):
        return value is pattern or value == pattern
    if isinstance(value, int | float) and isinstance(pattern, int | float):
        return float(value) == float(pattern)
    return value == pattern


def _check_value(path, axis: str, value: Any, allowed) -> None:
    if allowed is not None and not any(_match(value, a) for a in allowed):
        raise ConfigError(path, f"axes.{axis}", f"{value!r} is not one of: {', '.join(map(repr, allowed))}")


def _validate(spec: SpecFile, path) -> None:
    from mpd.planners import PLANNERS
    from mpd.tasks import load_task

    settings_fields = {f.name: f for f in dataclasses.fields(PlannerSettings)}
    for axis, values in spec.axes.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(path, f"axes.{axis}", "expected a non-empty list of values")
        if axis.startswith(PLANNER_PREFIX):
            name = axis[len(PLANNER_PREFIX) :]
            if name not in settings_fields:
                raise ConfigError(
                    path, f"axes.{axis}", f"unknown planner setting (allowed: {', '.join(settings_fields)})"
                )
            continue
        if axis not in AXES:
            allowed = ", ".join([*AXES, PLANNER_PREFIX + "<setting>"])
            raise ConfigError(path, f"axes.{axis}", f"unknown axis (allowed: {allowed})")
        for v in values:
            if axis == "method" and v not in PLANNERS:
                raise ConfigError(path, "axes.method", f"unknown method {v!r} (known: {', '.join(PLANNERS)})")
            if axis in ("n_samples", "seed") and (
                not isinstance(v, int) or isinstance(v, bool) or (axis == "n_samples" and v < 1)
            ):
                raise ConfigError(
                    path,
                    f"axes.{axis}",
                    f"{v!r} is not a {'positive ' if axis == 'n_samples' else ''}integer",
                )
            if axis == "rotation_deg" and (isinstance(v, bool) or not isinstance(v, int | float)):
                raise ConfigError(path, "axes.rotation_deg", f"{v!r} is not a number")
            _check_value(path, axis, v, AXES[axis])
    for k in ("task", "method"):
        if k not in spec.axes:
            raise ConfigError(path, f"axes.{k}", "missing required axis")
    for t in spec.axes["task"]:
        try:
            load_task(t)
        except ConfigError as e:
            raise ConfigError(path, "axes.task", f"{t!r}: {e.detail}") from None
        if t in spec.tasks and spec.tasks[t].contexts not in ("held-out", "sampled"):
            raise ConfigError(
                path, f"tasks.{t}.contexts", f"{spec.tasks[t].contexts!r} is not one of: 'held-out', 'sampled'"
            )
        if t not in spec.tasks:
            raise ConfigError(
                path, f"tasks.{t}", 'every task of axes.task needs a [tasks."NAME"] table with its dataset'
            )
    for i, ex in enumerate(spec.exclude):
        for k in ex:
            if k not in spec.axes and k not in DEFAULTS and k not in ("n_samples", "seed"):
                raise ConfigError(path, f"exclude[{i}].{k}", "not an axis of this spec")


def load_spec(name_or_path: str | Path) -> Spec:
    """Load and validate a spec by name (``benchmarks/specs/NAME.toml``) or path; errors name file and key."""
    p = Path(name_or_path)
    if p.suffix != ".toml" and not p.exists():
        p = SPEC_DIR / f"{name_or_path}.toml"
        if not p.exists():
            known = ", ".join(sorted(x.stem for x in SPEC_DIR.glob("*.toml")))
            raise ConfigError(name_or_path, "", f"unknown spec (known: {known}; or give a path to a .toml file)")
    raw = read_toml(p)
    data = from_dict(SpecFile, raw, source=p)
    _validate(data, p)
    spec = Spec(data, p, raw)
    _check_combinations(spec, p)
    return spec


def _check_combinations(spec: Spec, path) -> None:
    from mpd.planners import PLANNERS

    for cell in spec.cells():
        p = cell.p
        planner = PLANNERS[p["method"]]
        problem = planner.unsupported(p)
        if problem:
            raise ConfigError(
                path,
                "axes",
                f"impossible combination ({cell.label()}): {problem}; remove it with [[exclude]]",
            )
