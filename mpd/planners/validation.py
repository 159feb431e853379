"""The type and valid range of every planner setting, checked whenever settings are built: from the command line
(``mpd plan --set``), from a spec axis (``"planner.guide_lr"``) or from a task file (``[inference]``, ``[data]``).

The type comes from the annotation of :class:`~mpd.planners.settings.PlannerSettings` (``float | None``,
``Literal[...]`` ...); the range from :data:`RANGES`. A bad value is one line naming the setting, the value and what
is allowed, raised before any model is loaded::

    --set: guide_lr: -1 is not allowed (allowed: a number > 0; the step along the cost gradient ...)
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any

from mpd.planners.settings import PlannerSettings
from mpd.schema import ConfigError, check_type


@dataclass(frozen=True)
class Range:
    """``lo <= v`` (``lo < v`` when ``open_lo``) and ``v <= hi``; None: unbounded on that side."""

    lo: float | None = None
    hi: float | None = None
    open_lo: bool = False
    why: str = ""

    def ok(self, v: float) -> bool:
        if not math.isfinite(v):
            return False
        if self.lo is not None and (v <= self.lo if self.open_lo else v < self.lo):
            return False
        return self.hi is None or v <= self.hi

    def describe(self, integer: bool, nullable: bool = False) -> str:
        kind = "an integer" if integer else "a number"
        if self.lo is not None and self.hi is not None:
            text = f"{kind} in {'(' if self.open_lo else '['}{self.lo:g}, {self.hi:g}]"
        elif self.lo is not None:
            text = f"{kind} {'>' if self.open_lo else '>='} {self.lo:g}"
        else:
            text = kind
        text = f"allowed: {text}{' or null' if nullable else ''}"
        return f"{text}; {self.why}" if self.why else text


UNIT = Range(0.0, 1.0)
POSITIVE = Range(0.0, open_lo=True)
COUNT = Range(1.0)

# every numeric field of PlannerSettings (a test fails when a field has neither a range here nor a Literal type)
RANGES: dict[str, Range] = {
    "ddim_steps": Range(1.0, why="denoising steps"),
    "eta": Range(0.0, 1.0, why="DDIM noise scale (0 deterministic, 1 DDPM-like)"),
    "ddpm_variance_scale": Range(0.0, 1.0, why="scale of the DDPM noise variance"),
    "guide_fraction": Range(0.0, 1.0, why="the fraction of denoising steps that are guided"),
    "n_guided_steps": Range(0.0, why="guided denoising steps (used when guide_fraction is null)"),
    "n_inner_steps": Range(1.0, why="guidance updates per guided step (M)"),
    "prior_weight": Range(0.0, why="weight of the prior's noise prediction (lambda)"),
    "guide_lr": Range(0.0, open_lo=True, why="the step along the cost gradient (a negative one ascends the cost)"),
    "max_perturb": Range(0.0, open_lo=True, why="delta, the largest change per guided step"),
    "grad_clip": Range(0.0, open_lo=True, why="value clip of the cost gradient, null: off"),
    "ddpm_guide_fraction": Range(0.0, 1.0, why="the fraction of DDPM steps that are guided"),
    "ddpm_prior_weight": Range(0.0, why="weight of the prior's noise prediction in DDPM guidance"),
    "ddpm_n_inner_steps": Range(1.0, why="guidance updates per guided DDPM step"),
    "ddpm_guide_lr": Range(0.0, open_lo=True, why="the step along the cost gradient in DDPM guidance"),
    "opt_steps": Range(0.0, why="gradient steps after sampling (0: none)"),
    "opt_lr": Range(0.0, open_lo=True, why="the step of the gradient steps after sampling"),
    "opt_max_perturb": Range(0.0, open_lo=True, why="delta of the gradient steps after sampling"),
    "opt_grad_clip": Range(0.0, open_lo=True, why="value clip of the gradient after sampling, null: off"),
    "gp_sigma": Range(0.0, open_lo=True, why="GP prior std of the free control points"),
    "gp_lengthscale": Range(0.0, open_lo=True, why="GP prior lengthscale, phase units"),
    "rrt_time_limit": Range(0.0, open_lo=True, why="seconds per RRTConnect call"),
    "ik_restarts": Range(1.0, why="IK restarts for a goal configuration"),
}

_FIELDS = {f.name: f for f in dataclasses.fields(PlannerSettings)}
_HINTS = typing.get_type_hints(PlannerSettings)


def _is_int(tp: Any) -> bool:
    return tp is int or int in typing.get_args(tp) and float not in typing.get_args(tp)


def check_setting(name: str, value: Any, source: Any = "planner settings", where: str | None = None) -> Any:
    """The value of one planner setting, converted to its type (an int where a float is expected), or a
    :class:`ConfigError` naming ``source``, the setting (``where``, default its name), the value and what is
    allowed."""
    where = name if where is None else where
    if name not in _FIELDS:
        raise ConfigError(source, where, f"unknown planner setting (allowed: {', '.join(_FIELDS)})")
    tp, rule = _HINTS[name], RANGES.get(name)
    given = value
    try:
        value = check_type(tp, value, source, where)
    except ConfigError as e:
        hint = f" ({rule.describe(_is_int(tp), _nullable(tp))})" if rule else ""
        raise ConfigError(source, where, e.detail + hint) from None
    if rule is not None and value is not None and not rule.ok(float(value)):
        raise ConfigError(source, where, f"{given!r} is not allowed ({rule.describe(_is_int(tp), _nullable(tp))})")
    return value


def _nullable(tp: Any) -> bool:
    return type(None) in typing.get_args(tp)


def check_settings(values: dict[str, Any], source: Any = "planner settings", prefix: str = "") -> dict[str, Any]:
    """Every ``name: value`` checked (see :func:`check_setting`); returns the converted values."""
    return {k: check_setting(k, v, source, f"{prefix}{k}") for k, v in values.items()}


def check_task_settings(task) -> None:
    """The planner settings a task file sets (``[inference]``, ``[data]``), named by their place in the file."""
    check_setting("guide_fraction", task.spec.inference.guide_fraction, task.path, "inference.guide_fraction")
    check_setting("rrt_time_limit", task.spec.data.planner_time_limit, task.path, "data.planner_time_limit")


def parse_assignments(items: typing.Iterable[str], source: str = "--set") -> dict[str, Any]:
    """``NAME=VALUE`` strings (VALUE in JSON: ``0.5``, ``null``, ``"ddpm"``; a bare word is a string) to checked
    settings."""
    import json

    out: dict[str, Any] = {}
    for item in items:
        name, eq, text = item.partition("=")
        name = name.strip()
        if not eq or not name:
            raise ConfigError(source, item, "expected NAME=VALUE, e.g. guide_lr=0.5")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        out[name] = check_setting(name, value, source)
    return out


__all__ = ["RANGES", "Range", "check_setting", "check_settings", "check_task_settings", "parse_assignments"]
