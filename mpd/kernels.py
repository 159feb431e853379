"""The compiled CPU kernels (numba) in one registry, and the one switch between them and their torch references.

Each hot pass of the planner has a compiled fast path on the CPU and a torch (or numpy) reference that computes
the same numbers: the forward kinematics (``fk``), the collision, self-collision, end-effector and phase costs
(``collision``, ``self_collision``, ``ee_pose``, ``phase``) and the data checker's validity (``sphere``).
Every kernel module registers itself here (:func:`register`) with the one input check they share
(:func:`supported`) and a parity case that runs its public entry point on a realistic input, and every dispatch asks
:func:`active` whether to take the compiled path.

The switch: ``mode()`` is ``"compiled"`` (the default) or ``"torch"``, set for the process by the environment
variable ``MPD_KERNELS=torch|compiled`` and, for a block of code, by the context manager :func:`use` (for all the
kernels or the ones named; it overrides the environment variable and nests; its setting is the process's, seen by
every thread, and restored on exit)::

    with mpd.kernels.use("torch"):
        planner.plan(ctx)  # every cost, the FK and the checker on their torch / numpy references

``tests/test_kernels.py`` runs every registered kernel's parity case under both modes and compares them.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import torch

MODES = ("compiled", "torch")
ENV = "MPD_KERNELS"
# The modules that hold the kernels, imported by :func:`registered` (a lazy reach upwards, by name, like the
# package facade's): the one list of the kernels that exist.
MODULES = (
    "mpd.robots.fk_kernel",
    "mpd.costs.collision_kernel",
    "mpd.costs.self_collision_kernel",
    "mpd.costs.ee_kernel",
    "mpd.costs.phase_kernel",
    "mpd.data.sphere_kernel",
)


@dataclass(frozen=True)
class Kernel:
    """One compiled kernel: its ``name`` (what :func:`use` and :func:`active` take), the ``module`` that holds it,
    its torch ``reference`` (where the path taken in the ``torch`` mode lives, for the reader) and ``parity``: a
    factory ``parity(dtype) -> (run, tolerance)``, where ``run()`` calls the kernel's public entry point on a
    realistic input and returns its outputs ({name: tensor or array}) as the current mode computes them, and
    ``tolerance`` is the ``rtol``/``atol`` of the two modes' agreement (``tests/test_kernels.py``)."""

    name: str
    module: str
    reference: str
    parity: Callable[[Any], tuple[Callable[[], dict[str, Any]], dict[str, float]]]
    dtypes: tuple[str, ...] = ("float32", "float64")


_REGISTRY: dict[str, Kernel] = {}
_LOCK = threading.Lock()
_OVERRIDES: list[tuple[frozenset[str] | None, str]] = []  # the active use() blocks, innermost last
# how often each (kernel, path) was taken since the process started: what the tests read to see the switch work
runs: Counter = Counter()


def register(kernel: Kernel) -> Kernel:
    """Add a kernel to the registry (each kernel module calls this once, at import)."""
    if kernel.name in _REGISTRY and _REGISTRY[kernel.name].module != kernel.module:
        raise ValueError(f"two kernels named {kernel.name!r}: {_REGISTRY[kernel.name].module}, {kernel.module}")
    _REGISTRY[kernel.name] = kernel
    return kernel


def registered() -> dict[str, Kernel]:
    """Every kernel, by name (their modules imported on first use)."""
    for m in MODULES:
        importlib.import_module(m)
    return dict(_REGISTRY)


def _check(mode_: str) -> str:
    if mode_ not in MODES:
        raise ValueError(f"unknown kernel mode {mode_!r}: {' or '.join(MODES)}")
    return mode_


def mode(name: str | None = None) -> str:
    """The mode of kernel ``name`` (of all kernels when None): that of the innermost :func:`use` block that covers
    it, else ``MPD_KERNELS``, else ``"compiled"``."""
    for names, m in reversed(_OVERRIDES):
        if names is None or (name is not None and name in names):
            return m
    return _check(os.environ.get(ENV, "") or "compiled")


@contextlib.contextmanager
def use(mode_: str, *names: str) -> Iterator[None]:
    """Run the kernels ``names`` (all when none are named) in ``mode_`` ("compiled" or "torch") inside the block."""
    _check(mode_)
    if names:
        unknown = set(names) - set(registered())
        if unknown:
            raise ValueError(f"unknown kernels {sorted(unknown)}: {', '.join(sorted(_REGISTRY))}")
    entry = (frozenset(names) if names else None, mode_)
    with _LOCK:
        _OVERRIDES.append(entry)
    try:
        yield
    finally:
        with _LOCK:
            # remove this block's entry (the last one equal to it: blocks of other threads may have come since)
            for k in range(len(_OVERRIDES) - 1, -1, -1):
                if _OVERRIDES[k] is entry:
                    del _OVERRIDES[k]
                    break


def supported(*xs) -> bool:
    """The inputs every compiled kernel handles: CPU float32 / float64 tensors that need no autograd."""
    return all(
        x is not None and x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and not x.requires_grad
        for x in xs
    )


def active(name: str, *xs) -> bool:
    """Whether the dispatch of kernel ``name`` takes the compiled path for the inputs ``xs``: the switch says
    ``compiled`` and the inputs are :func:`supported`. Counted in :data:`runs`."""
    on = mode(name) == "compiled" and (not xs or supported(*xs))
    runs[name, "compiled" if on else "torch"] += 1
    return on
