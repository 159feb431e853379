"""Per-dimension min/max normalization to [-1, 1], the space the generative models and the guidance use."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

# A dimension whose training range is (almost) empty would divide by ~0; it is widened to [v - 1, v + 1]
# instead, so its constant value maps to 0 and its scale to raw units is 1.
_MIN_RANGE = 1e-8
# entries this far beyond +-1 count as inside the range for the gradient mask (the authors' tolerance)
CLIP_TOL = 1e-4


class Normalizer:
    """Affine map of the last axis: ``lo -> -1`` and ``hi -> +1``, one (lo, hi) pair per dimension.

    ``normalize(x) = 2 (x - lo) / (hi - lo) - 1`` and ``unnormalize`` its inverse. Since ``x_raw = centre +
    scale * x_norm`` with ``scale = (hi - lo) / 2``, a cost gradient maps as ``grad_norm = grad_raw * scale``
    (:meth:`grad_to_normalized`), and a step taken in normalized space is ``scale`` times larger in raw units.

    As the authors' limits normalizer, ``unnormalize`` clips to the data range first (x_norm to [-1, 1]): every
    sample a planner returns, and every point a cost is evaluated at, lies within the range of the training data.
    ``grad_to_normalized(g, x)`` then masks the entries of x outside [-1 - CLIP_TOL, 1 + CLIP_TOL], whose raw value
    does not move with them (the derivative of the clip), as the authors do.
    """

    def __init__(self, lo: Any, hi: Any):
        lo = np.asarray(lo, dtype=np.float64).reshape(-1)
        hi = np.asarray(hi, dtype=np.float64).reshape(-1)
        if lo.shape != hi.shape or lo.size == 0:
            raise ValueError(f"normalizer needs lo and hi of the same non-empty shape, got {lo.shape} and {hi.shape}")
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise ValueError("normalizer limits must be finite")
        if (hi < lo).any():
            raise ValueError(f"normalizer limits have hi < lo: lo={lo.tolist()}, hi={hi.tolist()}")
        empty = (hi - lo) < _MIN_RANGE
        self.lo = np.where(empty, lo - 1.0, lo)
        self.hi = np.where(empty, hi + 1.0, hi)
        self._cache: dict[tuple[torch.dtype, torch.device], tuple[torch.Tensor, torch.Tensor]] = {}

    @classmethod
    def fit(cls, values: np.ndarray | torch.Tensor) -> Normalizer:
        """Limits = min and max over every axis but the last (e.g. samples and control points)."""
        v = values.detach().cpu().numpy() if isinstance(values, torch.Tensor) else np.asarray(values)
        if v.ndim < 1 or v.shape[0] == 0:
            raise ValueError(f"cannot fit a normalizer on an empty array of shape {v.shape}")
        v = v.reshape(-1, v.shape[-1])
        # min and max in the array's own precision, then float64: the same limits as over a float64 copy (every
        # float32 is a float64), without that copy (3.5 GB for a paper-size dataset's control points)
        return cls(v.min(axis=0).astype(np.float64), v.max(axis=0).astype(np.float64))

    @property
    def dim(self) -> int:
        return int(self.lo.size)

    def to_dict(self) -> dict[str, list[float]]:
        return {"lo": self.lo.tolist(), "hi": self.hi.tolist()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Normalizer:
        if not isinstance(d, Mapping) or set(d) != {"lo", "hi"}:
            raise ValueError(f"a normalizer is a table with keys lo and hi, got {d!r}")
        return cls(d["lo"], d["hi"])

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Normalizer) and np.array_equal(self.lo, other.lo) and np.array_equal(self.hi, other.hi)

    def __repr__(self) -> str:
        return f"Normalizer(lo={np.round(self.lo, 4).tolist()}, hi={np.round(self.hi, 4).tolist()})"

    # -- maps ------------------------------------------------------------------------------------------------
    def _consts(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(centre, scale) as tensors of x's dtype and device, cached per (dtype, device)."""
        if x.shape[-1] != self.dim:
            raise ValueError(f"normalizer of dimension {self.dim} got a tensor of shape {tuple(x.shape)}")
        key = (x.dtype, x.device)
        if key not in self._cache:
            centre = torch.as_tensor((self.hi + self.lo) / 2, dtype=x.dtype, device=x.device)
            scale = torch.as_tensor((self.hi - self.lo) / 2, dtype=x.dtype, device=x.device)
            self._cache[key] = (centre, scale)
        return self._cache[key]

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        centre, scale = self._consts(x)
        return (x - centre) / scale

    def unnormalize(self, x: torch.Tensor, clip: bool = True) -> torch.Tensor:
        """Raw values of x; with ``clip`` (the default) x is first clipped to [-1, 1], i.e. to the data range."""
        centre, scale = self._consts(x)
        return (x.clamp(-1.0, 1.0) if clip else x) * scale + centre

    def scale(self, like: torch.Tensor) -> torch.Tensor:
        """d x_raw / d x_norm per dimension, ``(dim,)``, with the dtype and device of ``like``."""
        return self._consts(like)[1]

    def grad_to_normalized(self, grad_raw: torch.Tensor, x: torch.Tensor | None = None) -> torch.Tensor:
        """Chain rule: gradient of a cost w.r.t. raw values -> w.r.t. normalized values. With ``x`` (the normalized
        point the raw values came from, through the clipping :meth:`unnormalize`), entries of x beyond the range
        get zero gradient."""
        g = grad_raw * self._consts(grad_raw)[1]
        if x is None:
            return g
        return g * (x.abs() <= 1.0 + CLIP_TOL).to(g.dtype)

    def grad_to_raw(self, grad_norm: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`grad_to_normalized`."""
        return grad_norm / self._consts(grad_norm)[1]
