"""MPD and every baseline of the paper behind one interface.

    planner = make_planner("mpd", task, extra_objects=True, model=load_model(...))
    result = planner.plan(context, n_samples=100, seed=0)

Adding a planner: one file with a :class:`Planner` subclass decorated with ``@register``, plus its module name in
``_MODULES`` below.
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


def get_planner_class(name: str) -> type[Planner]:
    if name not in PLANNERS:
        raise ValueError(f"unknown planner {name!r} (known: {', '.join(PLANNERS)})")
    return PLANNERS[name]


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
    "get_planner_class",
    "make_planner",
    "planner_settings",
    "register",
]
