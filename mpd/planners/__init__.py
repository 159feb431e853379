"""MPD and every baseline of the paper behind one interface.

    planner = make_planner("mpd", task, extra_objects=True, model=load_model(...))
    result = planner.plan(context, n_samples=100, seed=0)

Adding a planner: one file with a :class:`Planner` subclass decorated with ``@register``, plus its module name in
``_MODULES`` below. A planner outside the repository is a :class:`Planner` subclass in the user's package, named
in a spec or on the command line as ``package.module:Class`` or registered through the ``mpd.planners`` entry point
group; ``mpd planners check NAME`` runs the conformance checks (:mod:`mpd.planners.conformance`) on it.
"""

from __future__ import annotations

import importlib

from mpd.planners.base import PLANNERS, Context, HistoryStep, Planner, PlanResult, Timer, register
from mpd.planners.settings import PRESETS, PlannerSettings, planner_settings

_MODULES = ("mpd", "dprior", "dprior_cost", "cvae", "cvae_cost", "gp_cost", "rrtconnect_cost")
for _m in _MODULES:
    importlib.import_module(f"mpd.planners.{_m}")

# the order of the paper's figures
METHOD_ORDER = ("gp-cost", "cvae", "cvae-cost", "dprior", "dprior-cost", "mpd", "rrtconnect-cost")


ENTRY_POINT_GROUP = "mpd.planners"


def _entry_points() -> dict:
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def planner_names() -> list[str]:
    """The built-in planners, then those installed through the ``mpd.planners`` entry point group."""
    return [*PLANNERS, *sorted(set(_entry_points()) - set(PLANNERS))]


def get_planner_class(name: str) -> type[Planner]:
    """A planner class by its registry name, by the name of an ``mpd.planners`` entry point of an installed package,
    or as ``package.module:Class`` (a class outside the repository, importable from ``sys.path``)."""
    if name in PLANNERS:
        return PLANNERS[name]
    where = None
    if ":" in name:
        module, _, attr = name.partition(":")
        where = f"{module}:{attr}"
        try:
            obj = importlib.import_module(module)
        except Exception as e:  # noqa: BLE001 - any import failure of a user's module is reported in one line
            raise ValueError(f"planner {name!r}: cannot import {module!r} ({type(e).__name__}: {e})") from None
        for part in attr.split("."):
            obj = getattr(obj, part, None)
            if obj is None:
                raise ValueError(f"planner {name!r}: module {module!r} has no {attr!r}") from None
    else:
        eps = _entry_points()
        if name not in eps:
            known = ", ".join(planner_names())
            raise ValueError(f"unknown planner {name!r} (known: {known}; or package.module:Class)")
        where = f"entry point {ENTRY_POINT_GROUP}:{name} = {eps[name].value}"
        try:
            obj = eps[name].load()
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"planner {name!r}: cannot load {where} ({type(e).__name__}: {e})") from None
    if not (isinstance(obj, type) and issubclass(obj, Planner)):
        raise ValueError(f"planner {name!r}: {where} is not a subclass of mpd.planners.Planner")
    if obj is Planner or not getattr(obj, "plan", None) or obj.plan is Planner.plan:
        raise ValueError(f"planner {name!r}: {where} does not implement plan(ctx, n_samples, seed, record_history)")
    return obj


def make_planner(
    name: str,
    task,
    *,
    extra_objects: bool = False,
    rotation_deg: float = 0.0,
    preset: str = "official",
    overrides: dict | None = None,
    parametrization: str = "bspline",
    model=None,
    device=None,
    data_range: tuple | None = None,
) -> Planner:
    """Build a planner for a task scene (training scene, extra objects, rotation) with a settings preset.

    ``data_range`` = (lo, hi) per joint of the training data's free control points: the normalized space of a
    planner without a model (GPprior+Cost, RRTConnect+Cost), as the authors' baselines use the dataset's; by default
    the joint limits. A planner with a model always uses the model's own range."""
    from mpd.device import default_device
    from mpd.trajectory import make_parametrization

    cls = get_planner_class(name)
    problem = cls.unsupported({"parametrization": parametrization})
    if problem:
        raise ValueError(problem)
    settings = planner_settings(task, preset, **(overrides or {}))
    if model is not None:
        if model.task_name != task.name:
            raise ValueError(f"model {model.path} was trained for {model.task_name!r}, not {task.name!r}")
        if model.parametrization != parametrization:
            raise ValueError(
                f"model {model.path} uses the {model.parametrization!r} parametrization, not {parametrization!r}"
            )
        if cls.model_kind is not None and model.kind != cls.model_kind:
            raise ValueError(
                f"planner {name!r} needs a {cls.model_kind} model, got a {model.kind} model ({model.path})"
            )
    device = device or (model.device if model is not None else default_device())
    env = task.env(extra_objects, rotation_deg)
    normalizer = None
    if data_range is not None and model is None:
        from mpd.models.normalizer import Normalizer

        normalizer = Normalizer(*data_range)
        if normalizer.dim != task.dof:
            raise ValueError(f"data_range has {normalizer.dim} dimensions, task {task.name} has {task.dof} joints")
    return cls(
        task,
        env,
        settings,
        make_parametrization(task, parametrization),
        model=model,
        device=device,
        normalizer=normalizer,
    )


__all__ = [
    "METHOD_ORDER",
    "PLANNERS",
    "PRESETS",
    "Context",
    "HistoryStep",
    "PlanResult",
    "Planner",
    "PlannerSettings",
    "Timer",
    "ENTRY_POINT_GROUP",
    "get_planner_class",
    "make_planner",
    "planner_names",
    "planner_settings",
    "register",
]
