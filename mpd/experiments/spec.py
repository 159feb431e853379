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

A task's models train with its table's ``profile`` (and ``train_steps``, when given); one model can take its own
(``diffusion``, ``cvae`` or ``<kind>-<parametrization>``; its identity is then the one ``mpd train --profile P
--steps N`` gives, so a shipped prior of that budget is found)::

    [tasks."EnvSimple2D-RobotPointMass2D"]
    dataset = "EnvSimple2D-RobotPointMass2D-paper"
    profile = "cpu"
    models."diffusion-bspline" = { profile = "paper", train_steps = 140000 }

A spec that differs from another in a few fields extends it and gives only those (tables merge key by key, lists and
values replace)::

    extends = "batch-sizes-cpu"
    name = "batch-sizes-gpu-priors"
    description = "..."

    [tasks."EnvSpheres3D-RobotPanda-cpu"]
    profile = "gpu"
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mpd.paths import SPECS_DIR
from mpd.planners.settings import PRESETS, PlannerSettings
from mpd.planners.validation import check_setting, check_task_settings
from mpd.schema import ConfigError, from_dict, read_toml, stable_hash
from mpd.trajectory import PARAMETRIZATIONS

SPEC_DIR = SPECS_DIR  # benchmarks/specs/ of the checkout, or the wheel's copy

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
# any field of the task's training profile is an axis too ("training.steps", "training.lr", ...): each value trains
# (or finds) its own model, the profile with that field replaced; methods without a model collapse these axes
TRAINING_PREFIX = "training."
# any field of the task's network spec is an axis too ("model.unet_dim", ...): each value trains (or finds) its own
# model with that field replaced (carried with the training overrides of a cell, under its "model." name)
MODEL_PREFIX = "model."


# the models a task's table can give a profile of their own: "<kind>" (every parametrization) or "<kind>-<par>"
MODEL_KINDS = ("diffusion", "cvae")
MODEL_KEYS = (*MODEL_KINDS, *(f"{k}-{p}" for k in MODEL_KINDS for p in PARAMETRIZATIONS))


@dataclass(frozen=True)
class ModelProfile:
    """One model's training profile and step count where they differ from its task's in a spec
    (``[tasks."NAME".models."diffusion-bspline"]``): a prior trained longer, by another recipe, beside the others."""

    profile: str | None = None
    train_steps: int | None = None  # override that profile's step count

    def validate(self) -> None:
        if self.train_steps is not None and (isinstance(self.train_steps, bool) or self.train_steps < 1):
            raise ConfigError("<dict>", "train_steps", f"{self.train_steps!r} is not a positive integer")


@dataclass(frozen=True)
class TaskSettings:
    """Which dataset and which training profile a task uses in this spec."""

    dataset: str
    profile: str = "cpu"
    # the CVAE's training profile where it differs from ``profile`` (e.g. diffusion priors of a GPU profile beside
    # a CVAE trained on this CPU); None: ``profile``
    cvae_profile: str | None = None
    train_steps: int | None = None  # override the profile's step count (e.g. a short demo training)
    n_contexts: int | None = None  # override the spec's number of evaluation contexts for this task
    # where the evaluation contexts come from (mpd.data.eval_contexts): "held-out" (the dataset's held-out paths,
    # as the authors; the default) or "sampled" (mpd's earlier dataset-independent contexts)
    contexts: str = "held-out"
    # in a rotated scene (a rotation_deg axis), turn the contexts with the obstacles (each context is then its
    # training-scene problem turned about the base: mpd.data.eval_contexts.for_scene); false (the default): the
    # contexts stay where they are and only the obstacles turn. Held-out contexts only.
    turn_contexts: bool = False
    # set by --scale (scale_spec), not in spec files: the dataset's contexts are multiplied by it (mpd.data, a
    # definition of its own with its own identity, never the full-size one)
    dataset_scale: float | None = None
    # per model ("diffusion-bspline", "cvae", ... : MODEL_KEYS): its own profile and step count, where they differ
    # from the ones above (e.g. the EnvSimple2D B-spline prior of the `paper` recipe at 140k steps beside the `cpu`
    # profile's waypoint prior and CVAE); the "<kind>-<parametrization>" entry before the "<kind>" one, field by field
    models: dict[str, ModelProfile] = field(default_factory=dict)

    def validate(self) -> None:
        for key, m in self.models.items():
            if key not in MODEL_KEYS:
                raise ConfigError("<dict>", f"models.{key}", f"not a model (one of: {', '.join(MODEL_KEYS)})")
            if m.profile is None and m.train_steps is None:
                raise ConfigError("<dict>", f"models.{key}", "gives neither profile nor train_steps")

    def _own(self, kind: str, parametrization: str | None, name: str) -> Any:
        """The value of ``name`` (a ModelProfile field) the most specific ``models`` entry of this model gives."""
        for key in (f"{kind}-{parametrization}", kind):
            m = self.models.get(key)
            if m is not None and getattr(m, name) is not None:
                return getattr(m, name)
        return None

    def profile_for(self, kind: str, parametrization: str | None = None) -> str:
        """The training profile of a model of ``kind`` ("diffusion" or "cvae") and ``parametrization``."""
        own = self._own(kind, parametrization, "profile")
        if own is not None:
            return own
        return self.cvae_profile if kind == "cvae" and self.cvae_profile is not None else self.profile

    def steps_for(self, kind: str, parametrization: str | None = None) -> int | None:
        """The step count that replaces the profile's for this model (None: the profile's)."""
        own = self._own(kind, parametrization, "train_steps")
        return own if own is not None else self.train_steps


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
    # the diffusion network's fast path (mpd.planners.settings.FAST_SETTINGS: compiled, bf16 where the device has
    # it), compiled once per worker before its first timed plan; planner.network_* axes override it, and false here
    # (or MPD_COMPILE=0 in the environment) runs the eager fp32 network. Every row records what ran
    # (info_network_compiled, info_network_precision).
    fast: bool = True


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

    def training_overrides(self) -> tuple[tuple[str, Any], ...]:
        """The training-profile fields this cell replaces, sorted, and its network fields as "model.<field>" (a
        hashable key of the cell's model)."""
        return tuple(
            (k[len(TRAINING_PREFIX) :] if k.startswith(TRAINING_PREFIX) else k, v)
            for k, v in self.params
            if k.startswith((TRAINING_PREFIX, MODEL_PREFIX)) and v is not None
        )

    def label(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self.params if v is not None)


class Spec:
    def __init__(self, data: SpecFile, path: Path | None, raw: dict, task_files: dict[str, Path] | None = None):
        self.data = data
        self.path = path
        self.raw = raw
        self.name = data.name
        self.hash = stable_hash(raw, n=12)
        # task name -> its file (the task axis holds names; a task given by path keeps its file here)
        self.task_files: dict[str, Path] = dict(task_files or {})

    def task_file(self, name: str) -> Path:
        """The file of a task of this spec (by its name)."""
        if name in self.task_files:
            return self.task_files[name]
        from mpd.tasks import resolve_task_path

        return resolve_task_path(name).resolve()

    def definition(self, task_name: str):
        """The dataset definition a task of this spec uses (a scaled copy under ``--scale``)."""
        from mpd.data.definition import load_definition

        ts = self.data.tasks[task_name]
        rd = load_definition(ts.dataset)
        return scaled_definition(rd, ts.dataset_scale, self.data.n_contexts if ts.n_contexts is None else ts.n_contexts)

    def task_name(self, entry: str) -> str:
        """The name of a task given by name or path (for ``--only task=...``)."""
        if entry in self.task_files:
            return entry
        try:
            f = _task_file(entry, self.path)
        except ConfigError:
            return entry
        return next((n for n, p in self.task_files.items() if p == f), entry)

    def __repr__(self) -> str:
        return f"Spec({self.name!r}, {len(self.cells())} cells, hash {self.hash})"

    def cells(self, only: dict[str, list[Any]] | None = None) -> list[Cell]:
        """The matrix: Cartesian product of the axes, minus excludes, restricted by ``only``, with axes that a method
        does not use collapsed to None (so e.g. `sampler` does not multiply GPprior+Cost cells)."""
        from mpd.planners import get_planner_class

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
            planner = get_planner_class(p["method"])
            for a in planner.unused_axes:
                if a in p:
                    p[a] = None
            if planner.model_kind is None:  # no model: the training and network axes do not apply
                for a in p:
                    if a.startswith((TRAINING_PREFIX, MODEL_PREFIX)):
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
    from mpd.planners import get_planner_class

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
            for v in values:
                check_setting(name, v, path, f"axes.{axis}")
            continue
        if axis.startswith(TRAINING_PREFIX):
            _check_training_axis(axis, values, path)
            continue
        if axis.startswith(MODEL_PREFIX):
            _check_model_axis(axis, values, path)
            continue
        if axis not in AXES:
            allowed = ", ".join(
                [*AXES, PLANNER_PREFIX + "<setting>", TRAINING_PREFIX + "<field>", MODEL_PREFIX + "<field>"]
            )
            raise ConfigError(path, f"axes.{axis}", f"unknown axis (allowed: {allowed})")
        for v in values:
            if axis == "method":
                if not isinstance(v, str):
                    raise ConfigError(path, "axes.method", f"{v!r} is not a planner name")
                try:
                    get_planner_class(v)  # a built-in, an installed entry point or package.module:Class
                except ValueError as e:
                    raise ConfigError(path, "axes.method", str(e)) from None
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
    for i, ex in enumerate(spec.exclude):
        for k in ex:
            if k not in spec.axes and k not in DEFAULTS and k not in ("n_samples", "seed"):
                raise ConfigError(path, f"exclude[{i}].{k}", "not an axis of this spec")


def _check_training_axis(axis: str, values: list, path) -> None:
    """A training axis names a TrainingSpec field, and each value has the field's type and an allowed value."""
    from mpd.models.train import check_training_spec
    from mpd.tasks.spec import TrainingSpec

    name = axis[len(TRAINING_PREFIX) :]
    fields = {f.name: f for f in dataclasses.fields(TrainingSpec)}
    if name not in fields:
        raise ConfigError(path, f"axes.{axis}", f"unknown training field (allowed: {', '.join(fields)})")
    base = TrainingSpec(batch_size=1, steps=1)
    kind = type(getattr(base, name))
    for v in values:
        ok = isinstance(v, kind) and not (isinstance(v, bool) and kind is not bool)
        if kind is float and isinstance(v, int) and not isinstance(v, bool):
            ok = True
        if not ok:
            raise ConfigError(path, f"axes.{axis}", f"{v!r} is not a {kind.__name__}")
        if name in ("steps", "batch_size") and v < 1:
            raise ConfigError(path, f"axes.{axis}", f"{v!r} must be at least 1")
        try:
            check_training_spec(dataclasses.replace(base, **{name: v}))
        except ValueError as e:
            raise ConfigError(path, f"axes.{axis}", str(e)) from None


def _check_model_axis(axis: str, values: list, path) -> None:
    """A network axis names an integer ModelSpec field (widths and sizes; ``unet_dim_mults``, a list, is not an axis)
    and each value is a positive integer (``goal_head_width`` takes 0 too: no goal head), or ``context_init``
    (one of ``mpd.tasks.spec.CONTEXT_INITS``)."""
    from mpd.tasks.spec import CONTEXT_INITS, ModelSpec

    name = axis[len(MODEL_PREFIX) :]
    fields = [f.name for f in dataclasses.fields(ModelSpec) if f.type in (int, "int")] + ["context_init"]
    if name not in fields:
        raise ConfigError(path, f"axes.{axis}", f"unknown network field (allowed: {', '.join(fields)})")
    if name == "context_init":
        for v in values:
            if v not in CONTEXT_INITS:
                raise ConfigError(path, f"axes.{axis}", f"{v!r} is not one of {', '.join(CONTEXT_INITS)}")
        return
    for v in values:
        least = 0 if name == "goal_head_width" else 1
        if not isinstance(v, int) or isinstance(v, bool) or v < least:
            raise ConfigError(
                path, f"axes.{axis}", f"{v!r} is not a {'non-negative' if least == 0 else 'positive'} integer"
            )


def _task_file(entry: str, spec_path: Path | None) -> Path:
    """A task entry of a spec (a bundled task's name or a path) as a file; a relative path is looked up next to the
    spec first, then from the working directory."""
    from mpd.tasks import resolve_task_path

    p = Path(entry)
    if spec_path is not None and not p.is_absolute() and (Path(spec_path).parent / p).is_file():
        return (Path(spec_path).parent / p).resolve()
    return resolve_task_path(entry).resolve()


def _resolve_tasks(spec: SpecFile, path) -> tuple[SpecFile, dict[str, Path]]:
    """Every task has one identity, the ``name`` of its file, whether the spec gives it by name or by path: the
    task axis, ``[[exclude]]`` and the ``[tasks."..."]`` tables (keyed by either) are rewritten to names. Returns
    the rewritten spec and the file of each task name."""
    from mpd.tasks import load_task

    files: dict[str, Path] = {}
    alias: dict[str, str] = {}  # every way the spec names a task -> the task's name
    for t in spec.axes["task"]:
        if not isinstance(t, str):
            raise ConfigError(path, "axes.task", f"{t!r} is not a task name or a path to a task file")
        try:
            f = _task_file(t, path)
            task = load_task(f)
        except ConfigError as e:
            raise ConfigError(path, "axes.task", f"{t!r}: {e.detail}") from None
        check_task_settings(task)  # its [inference] and [data] planner settings, before anything is built
        if task.name in files and files[task.name] != f:
            raise ConfigError(path, "axes.task", f"two task files are named {task.name!r}: {files[task.name]} and {f}")
        files[task.name] = f
        alias[t] = alias[task.name] = task.name
    tables: dict[str, TaskSettings] = {}
    keys: dict[str, str] = {}
    for key, ts in spec.tasks.items():
        name = alias.get(key)
        if name is None:  # a table keyed by another spelling of a path (relative vs absolute)
            try:
                name = next((n for n, f in files.items() if _task_file(key, path) == f), None)
            except ConfigError:
                name = None
        if name is None:
            continue  # a table of a task this spec does not run (kept for --only-style edits of the axis)
        if name in tables:
            raise ConfigError(
                path, f"tasks.{key}", f"task {name!r} has two tables, [tasks.{keys[name]!r}] and [tasks.{key!r}]"
            )
        if ts.contexts not in ("held-out", "sampled"):
            raise ConfigError(path, f"tasks.{key}.contexts", f"{ts.contexts!r} is not one of: 'held-out', 'sampled'")
        profiles = load_task(files[name]).spec.training if ts.models else {}
        for model, m in ts.models.items():
            if m.profile is not None and m.profile not in profiles:
                why = f"{m.profile!r} is not a training profile of {name} (it has: {', '.join(profiles)})"
                raise ConfigError(path, f"tasks.{key}.models.{model}.profile", why)
        if ts.turn_contexts and ts.contexts != "held-out":
            why = "turns held-out contexts only (contexts = 'held-out')"
            raise ConfigError(path, f"tasks.{key}.turn_contexts", why)
        near = Path(path).parent / ts.dataset if path is not None else None
        if near is not None and not Path(ts.dataset).is_absolute() and near.is_file():
            ts = dataclasses.replace(ts, dataset=str(near.resolve()))  # a definition next to the spec
        tables[name], keys[name] = ts, key
    for t in spec.axes["task"]:
        if alias[t] not in tables:
            raise ConfigError(
                path,
                f"tasks.{alias[t]}",
                f'every task of axes.task needs a [tasks."NAME"] table with its dataset (NAME: {alias[t]!r} or '
                "the path given in axes.task)",
            )
    names = list(dict.fromkeys(alias[t] for t in spec.axes["task"]))
    exclude = [
        {
            k: ([alias.get(x, x) for x in v] if isinstance(v, list) else alias.get(v, v)) if k == "task" else v
            for k, v in ex.items()
        }
        for ex in spec.exclude
    ]
    out = dataclasses.replace(spec, axes={**spec.axes, "task": names}, tasks=tables, exclude=exclude)
    return out, files


def _spec_path(name_or_path: str | Path, near: Path | None = None) -> Path | None:
    """A spec given by name (``benchmarks/specs/NAME.toml``) or path (relative: next to ``near`` first); None if
    there is no such file."""
    p = Path(name_or_path)
    if near is not None and not p.is_absolute() and (near.parent / p).is_file():
        return near.parent / p
    if p.suffix == ".toml" or p.exists():
        return p if p.is_file() else None
    p = SPEC_DIR / f"{name_or_path}.toml"
    return p if p.is_file() else None


def _known_specs() -> str:
    return ", ".join(sorted(x.stem for x in SPEC_DIR.glob("*.toml")))


def _merge(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s values: tables merge key by key, anything else (lists included) is replaced."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def resolve_extends(path: Path, _chain: tuple[Path, ...] = ()) -> dict:
    """The content of the spec file at ``path`` with its ``extends`` resolved: the parent spec (a name in
    ``benchmarks/specs/`` or a path, relative to this file) resolved the same way, then this file's fields over it
    (tables merged key by key, values and lists replaced). A spec that extends another names itself (``name``). The
    result holds no ``extends``: it is what the spec's hash and a run's manifest record, so a spec written as
    ``extends`` plus its differences has the identity of the full copy it replaces."""
    raw = read_toml(path)
    if "extends" not in raw:
        return raw
    parent = raw.pop("extends")
    if not isinstance(parent, str):
        raise ConfigError(path, "extends", f"{parent!r} is not a spec name or a path to a spec file")
    if "name" not in raw:
        raise ConfigError(path, "name", f"a spec that extends {parent!r} needs its own name")
    parent_path = _spec_path(parent, near=path)
    if parent_path is None:
        raise ConfigError(
            path, "extends", f"unknown spec {parent!r} (known: {_known_specs()}; or a path to a .toml file)"
        )
    chain = (*_chain, Path(path).resolve())
    if parent_path.resolve() in chain:
        cycle = " -> ".join(p.stem for p in (*chain, parent_path.resolve()))
        raise ConfigError(path, "extends", f"specs extend each other in a cycle: {cycle}")
    return _merge(resolve_extends(parent_path, chain), raw)


def load_spec(name_or_path: str | Path) -> Spec:
    """Load and validate a spec by name (``benchmarks/specs/NAME.toml``) or path; errors name file and key. A spec
    may extend another (``extends = "NAME"`` plus the fields that differ; :func:`resolve_extends`)."""
    p = _spec_path(name_or_path)
    if p is None:
        if Path(name_or_path).suffix == ".toml":
            raise ConfigError(name_or_path, "", "file not found")
        raise ConfigError(name_or_path, "", f"unknown spec (known: {_known_specs()}; or give a path to a .toml file)")
    raw = resolve_extends(p)
    data = from_dict(SpecFile, raw, source=p)
    _validate(data, p)
    data, task_files = _resolve_tasks(data, p)
    spec = Spec(data, p, raw, task_files)
    _check_combinations(spec, p)
    return spec


def _check_combinations(spec: Spec, path) -> None:
    from mpd.planners import get_planner_class

    for cell in spec.cells():
        p = cell.p
        planner = get_planner_class(p["method"])
        problem = planner.unsupported(p)
        if problem:
            raise ConfigError(
                path,
                "axes",
                f"impossible combination ({cell.label()}): {problem}; remove it with [[exclude]]",
            )


# --scale: the floors that keep a shrunk run meaningful end to end
SCALE_MIN_CONTEXTS, SCALE_MIN_SAMPLES, SCALE_MIN_STEPS, SCALE_MIN_DATASET = 2, 8, 20, 128


def _scaled(n: int, factor: float, floor: int) -> int:
    return max(min(floor, n), math.ceil(n * factor - 1e-9))  # 3e6 x 1e-5 is 30.000000000000004


def scale_spec(spec: Spec, factor: float) -> Spec:
    """The same spec with every cell shrunk by ``factor`` (0 < factor <= 1): evaluation contexts, samples, training
    steps (of the profile and of `training.steps` axes) and dataset size, each with a floor (2 contexts, 8 samples,
    20 steps, 128 dataset contexts). How a user tries a cluster (or a laptop) on a big spec before the real run: the
    matrix, the methods and the pipeline are unchanged; its results are not the spec's. Its own hash, run folder,
    dataset identities and model identities, so nothing full-size is touched."""
    if not 0 < factor <= 1:
        raise ConfigError("--scale", "", f"must be in (0, 1], got {factor}")
    if factor == 1:
        return spec
    from mpd.tasks import load_task

    d = spec.data
    tasks = {}
    for name, ts in d.tasks.items():
        task = load_task(spec.task_file(name))
        steps = ts.train_steps or task.training(ts.profile).steps
        models = {
            key: dataclasses.replace(
                m,
                train_steps=_scaled(
                    ts.steps_for(*key.split("-")) or task.training(ts.profile_for(*key.split("-"))).steps,
                    factor,
                    SCALE_MIN_STEPS,
                ),
            )
            for key, m in ts.models.items()
        }
        tasks[name] = dataclasses.replace(
            ts,
            train_steps=_scaled(steps, factor, SCALE_MIN_STEPS),
            models=models,
            n_contexts=None if ts.n_contexts is None else _scaled(ts.n_contexts, factor, SCALE_MIN_CONTEXTS),
            dataset_scale=factor,
        )
    axes = dict(d.axes)
    if "n_samples" in axes:
        axes["n_samples"] = sorted({_scaled(int(n), factor, SCALE_MIN_SAMPLES) for n in axes["n_samples"]})
    if f"{TRAINING_PREFIX}steps" in axes:
        axes[f"{TRAINING_PREFIX}steps"] = sorted(
            {_scaled(int(n), factor, SCALE_MIN_STEPS) for n in axes[f"{TRAINING_PREFIX}steps"]}
        )
    data = dataclasses.replace(
        d,
        axes=axes,
        tasks=tasks,
        n_contexts=_scaled(d.n_contexts, factor, SCALE_MIN_CONTEXTS),
        n_samples=_scaled(d.n_samples, factor, SCALE_MIN_SAMPLES),
    )
    raw = {**spec.raw, "scale": factor}
    out = Spec(data, spec.path, raw, spec.task_files)
    out.name = f"{spec.name}-x{factor:g}"
    return out


def scaled_definition(rd, factor: float | None, n_eval: int):
    """A dataset definition shrunk by ``factor`` (None: ``rd`` itself): its contexts (>= 128) in >= 4 chunks, and
    held-out fractions raised so that it holds >= 16 x ``n_eval`` held-out contexts (at most half of it). A
    definition of its own (name ``<name>-x<factor>``, its own identity and cache folder; no lock file is written)."""
    if factor is None or factor >= 1:
        return rd
    from mpd.data.definition import ResolvedDefinition, identity_of

    defn = rd.definition
    n = _scaled(defn.n_contexts, factor, SCALE_MIN_DATASET)
    # 16 held-out contexts per evaluation context: as few as 1 in 8 held-out paths passes the evaluation's minimum
    # start-goal distance (EnvNarrowPassageDense2D)
    held = min(0.25, max(defn.split.val + defn.split.test, 16.0 * n_eval / n) / 2)
    split = dataclasses.replace(defn.split, val=max(defn.split.val, held), test=max(defn.split.test, held))
    new = dataclasses.replace(
        defn, name=f"{defn.name}-x{factor:g}", n_contexts=n, chunk_size=max(1, math.ceil(n / 4)), split=split
    )
    return ResolvedDefinition(new, rd.task, None, identity_of(new, rd.task))
