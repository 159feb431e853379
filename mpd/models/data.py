"""What the trainer consumes: raw (unnormalized) free control points with their contexts and splits."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mpd.models.context import UNNORMALIZED_KEYS, context_kind_of, context_shapes
from mpd.models.normalizer import Normalizer
from mpd.schema import canonical_json

if TYPE_CHECKING:
    from mpd.tasks import Task

SPLIT_TRAIN, SPLIT_VAL, SPLIT_TEST = 0, 1, 2
SPLIT_NAMES = {SPLIT_TRAIN: "train", SPLIT_VAL: "val", SPLIT_TEST: "test"}
_SAFE_NAME = re.compile(r"[A-Za-z0-9_.-]+")


@dataclass(frozen=True, eq=False)
class TrainingArrays:
    """A training set for one task and one trajectory parametrization.

    ``x``: ``(N, H, d)`` float32 free control points (B-spline inner control points, or the free waypoints),
    raw units. ``context``: ``q_start (N, d)`` and either ``q_goal (N, d)`` or ``ee_pos (N, 3)`` + ``ee_rot
    (N, 3, 3)``. ``split``: ``(N,)`` int8, 0 train / 1 val / 2 test. The hashes and the parametrization name
    and settings identify what made the arrays; they go into the model's identity and checkpoint.
    """

    x: np.ndarray
    context: dict[str, np.ndarray]
    split: np.ndarray
    task_name: str
    task_hash: str
    dataset_hash: str
    parametrization: str
    parametrization_settings: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    def _fail(self, where: str, message: str) -> None:
        raise ValueError(f"TrainingArrays({self.task_name!r}).{where}: {message}")

    def validate(self) -> None:
        if not isinstance(self.x, np.ndarray) or self.x.ndim != 3 or 0 in self.x.shape:
            self._fail("x", f"expected a non-empty (N, H, d) array, got {getattr(self.x, 'shape', type(self.x))}")
        if not np.isfinite(self.x).all():
            self._fail("x", "contains NaN or inf")
        n, _, dof = self.x.shape
        try:
            kind = context_kind_of(set(self.context))
        except ValueError as e:
            self._fail("context", str(e))
        for key, shape in context_shapes(kind, dof).items():
            v = self.context[key]
            if not isinstance(v, np.ndarray) or v.shape != (n, *shape):
                self._fail(f"context[{key!r}]", f"expected shape {(n, *shape)}, got {getattr(v, 'shape', type(v))}")
            if not np.isfinite(v).all():
                self._fail(f"context[{key!r}]", "contains NaN or inf")
        if not isinstance(self.split, np.ndarray) or self.split.shape != (n,):
            self._fail("split", f"expected shape ({n},), got {getattr(self.split, 'shape', type(self.split))}")
        bad = set(np.unique(self.split).tolist()) - set(SPLIT_NAMES)
        if bad:
            self._fail("split", f"values must be 0 (train), 1 (val) or 2 (test), found {sorted(bad)}")
        if not (self.split == SPLIT_TRAIN).any():
            self._fail("split", "no training samples (split == 0)")
        for name in ("task_name", "task_hash", "dataset_hash", "parametrization"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                self._fail(name, "must be a non-empty string")
        for name in ("task_name", "parametrization"):  # they name folders of the model cache
            if not _SAFE_NAME.fullmatch(getattr(self, name)):
                self._fail(name, f"{getattr(self, name)!r} may only contain letters, digits, '_', '-' and '.'")
        try:
            canonical_json(self.parametrization_settings)
        except TypeError as e:
            self._fail("parametrization_settings", f"must be JSON-able: {e}")

    @property
    def n(self) -> int:
        return int(self.x.shape[0])

    @property
    def horizon(self) -> int:
        return int(self.x.shape[1])

    @property
    def dof(self) -> int:
        return int(self.x.shape[2])

    @property
    def context_kind(self) -> str:
        return context_kind_of(set(self.context))

    def indices(self, split: int) -> np.ndarray:
        return np.flatnonzero(self.split == split)


def fit_normalizers(arrays: TrainingArrays) -> tuple[Normalizer, dict[str, Normalizer]]:
    """Min/max normalizers from the training split: x per joint (over samples and control points), every
    context field per dimension except the rotation matrix."""
    train = arrays.indices(SPLIT_TRAIN)
    x_norm = Normalizer.fit(arrays.x[train])
    ctx = {k: Normalizer.fit(v[train]) for k, v in arrays.context.items() if k not in UNNORMALIZED_KEYS}
    return x_norm, ctx


def training_arrays(task: Task, dataset, parametrization: str):
    """The free rows of every dataset path in a parametrization, with contexts and splits, for model training."""
    from mpd.trajectory import make_parametrization

    param = make_parametrization(task, parametrization)
    if parametrization == "bspline":
        w = dataset.control_points
    elif hasattr(dataset.paths, "blocks"):  # fitted block by block: the dense paths are never all in memory
        w = None
        for start, stop, block in dataset.paths.blocks():
            fit = param.fit(block)
            if w is None:
                w = np.empty((len(dataset.paths), *fit.shape[1:]), dtype=fit.dtype)
            w[start:stop] = fit
        if w is None:
            w = param.fit(np.asarray(dataset.paths))
    else:
        w = param.fit(dataset.paths)
    x = np.ascontiguousarray(param.free_rows(w), dtype=np.float32)
    ctx = {"q_start": dataset.q_start.astype(np.float32)}
    if task.ee_goal:
        ctx["ee_pos"] = dataset.ee_pos.astype(np.float32)
        ctx["ee_rot"] = dataset.ee_rot.astype(np.float32)
    else:
        ctx["q_goal"] = dataset.q_goal.astype(np.float32)
    return TrainingArrays(
        x=x,
        context=ctx,
        split=dataset.split.astype(np.int8),
        task_name=task.name,
        task_hash=task.file_hash,
        dataset_hash=dataset.info["content_hash"],
        parametrization=parametrization,
        parametrization_settings=param.settings(),
    )
