"""Checkpoints: everything needed to sample a trained prior, read back with clear errors.

A checkpoint is a ``torch.save`` of plain data (tensors, dicts, lists, strings, numbers), so it is loaded with
``weights_only=True`` (no pickle code execution). It holds the kind, specs, weights, EMA weights, normalizers,
task and dataset identity, parametrization and its settings, seed, step and provenance.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from mpd.models.context import UNNORMALIZED_KEYS, context_shapes
from mpd.models.cvae import CVAE
from mpd.models.diffusion import DiffusionModel
from mpd.models.normalizer import Normalizer
from mpd.schema import ConfigError, from_dict
from mpd.tasks.spec import ModelSpec, TrainingSpec

FORMAT = "mpd-model"
FORMAT_VERSION = 1
KINDS = ("diffusion", "cvae")
MODEL_FILE = "model.pt"
LAST_FILE = "last.pt"
META_FILE = "meta.json"

REQUIRED_KEYS = (
    "kind", "identity", "model_spec", "training_spec", "seed", "dof", "horizon", "context_kind", "task_name",
    "task_hash", "dataset_hash", "parametrization", "parametrization_settings", "normalizers", "weights",
    "ema_weights", "step", "provenance",
)  # fmt: skip


def build_network(kind: str, dof: int, horizon: int, context_kind: str, spec: ModelSpec) -> nn.Module:
    if kind == "diffusion":
        return DiffusionModel(dof, horizon, context_kind, spec)
    if kind == "cvae":
        return CVAE(dof, horizon, context_kind, spec)
    raise ValueError(f"unknown model kind {kind!r} (known: {', '.join(KINDS)})")


def save_atomic(obj: Any, path: Path) -> None:
    """``torch.save`` to a temporary name in the same folder, then rename: never a half-written final file."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        try:
            torch.save(obj, tmp)
        except RuntimeError as e:  # torch's zip writer reports a full disk as "unexpected pos ..."
            import errno
            import shutil

            if shutil.disk_usage(tmp.parent).free < (tmp.stat().st_size if tmp.exists() else 0) + (1 << 20):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path)) from e
            raise
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint file and check its envelope; problems raise :class:`ConfigError` naming the file."""
    path = Path(path)
    if path.is_dir():
        path = path / MODEL_FILE
    if not path.is_file():
        raise ConfigError(path, "", "checkpoint file not found")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # zip / unpickling errors of a truncated or foreign file
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(path, "", f"not a readable mpd checkpoint (truncated or corrupted file?): {reason}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ConfigError(path, "", f"not an mpd model checkpoint (no format = {FORMAT!r} marker)")
    if ckpt.get("format_version") != FORMAT_VERSION:
        raise ConfigError(
            path,
            "format_version",
            f"checkpoint format {ckpt.get('format_version')!r}, this mpd reads {FORMAT_VERSION}",
        )
    missing = [k for k in REQUIRED_KEYS if k not in ckpt]
    if missing:
        raise ConfigError(path, missing[0], "missing from the checkpoint (incomplete file?)")
    if ckpt["kind"] not in KINDS:
        raise ConfigError(path, "kind", f"unknown model kind {ckpt['kind']!r} (known: {', '.join(KINDS)})")
    ckpt["_path"] = str(path)
    return ckpt


def _as_tensor(v: Any, device: torch.device) -> torch.Tensor:
    return (
        v.to(device=device, dtype=torch.float32)
        if isinstance(v, torch.Tensor)
        else torch.as_tensor(np.asarray(v), dtype=torch.float32, device=device)
    )


@dataclass
class LoadedModel:
    """A trained prior ready to sample: the network (EMA weights, eval mode), normalizers and metadata.

    ``network`` works in normalized space: a :class:`DiffusionModel` (``network(x_t, t, context)`` predicts
    the noise; planners combine it with :func:`mpd.models.diffusion.ddim_step`) or a :class:`CVAE`.
    """

    kind: str
    network: nn.Module
    x_normalizer: Normalizer
    context_normalizers: dict[str, Normalizer]
    meta: dict[str, Any]
    path: Path
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def task_name(self) -> str:
        return self.meta["task_name"]

    def to(self, device: torch.device | str) -> LoadedModel:
        """This model on ``device``: itself when it is there already, else a copy (the network copied, so that a
        planner on a GPU never moves the network of a caller who plans on the CPU with the same model)."""
        device = torch.device(device)
        if device.type == "cuda" and device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        here = next(self.network.parameters(), None)
        if here is not None and here.device == device and self.device == device:
            return self
        net = copy.deepcopy(self.network).to(device)
        return dataclasses.replace(self, network=net, device=device)

    @property
    def parametrization(self) -> str:
        return self.meta["parametrization"]

    @property
    def horizon(self) -> int:
        return int(self.meta["horizon"])

    @property
    def dof(self) -> int:
        return int(self.meta["dof"])

    @property
    def context_kind(self) -> str:
        return self.meta["context_kind"]

    def normalize_context(self, context: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """Raw context (arrays or tensors, batched or a single one) -> normalized float32 tensors on the
        model's device, each with a batch axis."""
        out = {}
        for key, shape in context_shapes(self.context_kind, self.dof).items():
            if key not in context:
                raise ValueError(f"{self.path}: a {self.context_kind} context needs {key!r}, got {sorted(context)}")
            v = _as_tensor(context[key], self.device)
            if tuple(v.shape) == shape:
                v = v.unsqueeze(0)
            if tuple(v.shape[1:]) != shape:
                raise ValueError(f"context[{key!r}] must have shape {shape} or (B, *{shape}), got {tuple(v.shape)}")
            out[key] = v if key in UNNORMALIZED_KEYS else self.context_normalizers[key].normalize(v)
        return out

    def sample(
        self,
        context: Mapping[str, Any],
        n: int,
        *,
        generator: torch.Generator | None = None,
        normalized: bool = False,
        **sampler_kwargs: Any,
    ) -> torch.Tensor | tuple[torch.Tensor, list[torch.Tensor]]:
        """``(n, H, d)`` unguided samples for one raw context, in raw units (``normalized=False``) or in the
        model's [-1, 1] space. Diffusion keywords (sampler, steps, schedule, variant, eta, variance_scale,
        return_history) are those of :func:`mpd.models.diffusion.sample`."""
        ctx = self.normalize_context(context)
        if self.kind == "cvae":
            if sampler_kwargs:
                raise TypeError(f"a CVAE sample takes no sampler settings, got {sorted(sampler_kwargs)}")
            result = self.network.sample(ctx, n, generator=generator)
        else:
            result = self.network.sample(ctx, n, generator=generator, **sampler_kwargs)
        if normalized:
            return result
        if isinstance(result, tuple):
            x, history = result
            return self.x_normalizer.unnormalize(x), [self.x_normalizer.unnormalize(h) for h in history]
        return self.x_normalizer.unnormalize(result)


def checkpoint_meta(ckpt: Mapping[str, Any]) -> dict[str, Any]:
    """Everything in a checkpoint but the tensors and optimizer state."""
    skip = {"weights", "ema_weights", "optimizer", "rng", "_path"}
    return {k: v for k, v in ckpt.items() if k not in skip}


def load_model(
    path: str | Path,
    expect_task: str | None = None,
    expect_parametrization: str | None = None,
    device: torch.device | str | None = None,
) -> LoadedModel:
    """Load a checkpoint (a ``model.pt`` or its folder) for sampling, with the EMA weights.

    ``expect_task`` / ``expect_parametrization``: raise :class:`ConfigError` when the checkpoint was trained
    for another task (name) or parametrization; a truncated, corrupted or foreign file also raises it.
    """
    from mpd.device import default_device

    ckpt = read_checkpoint(path)
    path = Path(ckpt["_path"])
    if expect_task is not None and ckpt["task_name"] != expect_task:
        raise ConfigError(path, "task_name", f"checkpoint is for task {ckpt['task_name']!r}, expected {expect_task!r}")
    if expect_parametrization is not None and ckpt["parametrization"] != expect_parametrization:
        raise ConfigError(
            path,
            "parametrization",
            f"checkpoint is for parametrization {ckpt['parametrization']!r}, expected {expect_parametrization!r}",
        )
    spec = from_dict(ModelSpec, ckpt["model_spec"], source=path, where="model_spec")
    from_dict(TrainingSpec, ckpt["training_spec"], source=path, where="training_spec")
    try:
        x_norm = Normalizer.from_dict(ckpt["normalizers"]["x"])
        ctx_norms = {k: Normalizer.from_dict(v) for k, v in ckpt["normalizers"]["context"].items()}
        for key in context_shapes(ckpt["context_kind"], int(ckpt["dof"])):
            if key not in UNNORMALIZED_KEYS and key not in ctx_norms:
                raise KeyError(f"no normalizer for context field {key!r}")
        net = build_network(ckpt["kind"], int(ckpt["dof"]), int(ckpt["horizon"]), ckpt["context_kind"], spec)
        net.load_state_dict(ckpt["ema_weights"])
    except (KeyError, ValueError, RuntimeError, TypeError) as e:
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(path, "", f"inconsistent checkpoint contents: {reason}") from None
    device = torch.device(device) if device is not None else default_device()
    net = net.to(device).eval().requires_grad_(False)
    return LoadedModel(ckpt["kind"], net, x_norm, ctx_norms, checkpoint_meta(ckpt), path, device)
