"""Checks of a planning problem given by a user (the Python API and ``mpd plan``), before any work: one line naming
the argument for each problem (a wrong shape, NaN, a joint outside its limits, a configuration in collision)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


class PlanningInputError(ValueError):
    """A planning input is unusable; ``argument`` names it (``q_start``, ``goal``, ``obstacles[2].radius`` ...)."""

    def __init__(self, argument: str, detail: str):
        self.argument = argument
        self.detail = detail
        super().__init__(f"{argument}: {detail}")


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def shape_of(value: Any) -> tuple[int, ...] | None:
    """The array shape of ``value``, or None where it is not one (a ragged list, an object numpy cannot read)."""
    try:
        return tuple(np.shape(value))
    except (TypeError, ValueError):
        return None


def as_array(value: Any, argument: str, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a finite float64 array of exactly ``shape`` (a list, tuple, numpy array or tensor)."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().double().numpy()
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise PlanningInputError(argument, f"{value!r} is not an array of numbers") from None
    if a.shape != shape:
        want = "x".join(str(s) for s in shape) or "a scalar"
        raise PlanningInputError(argument, f"has shape {tuple(a.shape)}, expected {want}")
    bad = ~np.isfinite(a)
    if bad.any():
        i = np.argwhere(bad)[0]
        where = f"entry {', '.join(str(int(k)) for k in i)} is" if a.ndim else "is"
        raise PlanningInputError(argument, f"{where} {_fmt(float(a[tuple(i)]))} (not a finite number)")
    return a


def float32_within(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``q`` in float32, each entry the float32 nearest to it that lies within [lo, hi] (float64 bounds): a
    configuration on a joint limit (MotionBenchMaker's goals, e.g.) would otherwise round to just beyond it, and every
    trajectory ending there would break the limit by 1e-7 rad."""
    x = np.asarray(q, dtype=np.float32)
    x = np.where(x.astype(np.float64) < lo, np.nextafter(x, np.float32(np.inf)), x)
    return np.where(x.astype(np.float64) > hi, np.nextafter(x, np.float32(-np.inf)), x).astype(np.float32)


def check_configuration(task, q: np.ndarray, argument: str, checker=None) -> None:
    """A joint configuration within the limits and, with a ground-truth ``checker`` (:class:`CollisionChecker`),
    free of collisions with its scene and of self collisions."""
    lo, hi = task.robot.q_min.double().numpy(), task.robot.q_max.double().numpy()
    out = np.nonzero((q < lo) | (q > hi))[0]
    if len(out):
        j = int(out[0])
        raise PlanningInputError(
            argument, f"joint {j} = {_fmt(q[j])} is outside its limits [{_fmt(lo[j])}, {_fmt(hi[j])}]"
        )
    if checker is None:
        return
    v = checker.configs(torch.as_tensor(q, dtype=torch.float64)[None])
    shown = "[" + ", ".join(_fmt(x) for x in q) + "]"
    if not bool(v.env_free[0]):
        raise PlanningInputError(argument, f"{shown} is in collision with the environment")
    if not bool(v.self_free[0]):
        raise PlanningInputError(argument, f"{shown} is in self collision")


__all__ = ["PlanningInputError", "as_array", "check_configuration"]
