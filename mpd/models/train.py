"""Training of the diffusion prior and of the CVAE baseline: cached by identity, resumable, repeatable.

A model's identity is ``stable_hash(dataset_hash, kind, parametrization, parametrization_settings, model spec,
training spec, seed)``; it lives in ``<cache>/models/<task>/<kind>-<parametrization>-<identity>/`` with
``model.pt`` (final), ``last.pt`` (while training, for resuming) and ``meta.json``. Optimizer: AdamW with
gradient-norm clipping; EMA of the weights (kept equal to the weights before ``ema_start``); i.i.d.
minibatches drawn with replacement. Every random number comes from one generator seeded with ``seed``
(network init from ``seed`` too), and its state is checkpointed, so an interrupted and resumed run ends with
the same weights as an uninterrupted one.

:func:`train_model` puts together parts with one job each: ``_find_or_claim`` (the finished model, a shipped prior
installed, or the lock to train it), :class:`TrainingState` (fresh, or resumed from ``last.pt`` or a ``wsd``
trunk's snapshot), a step object of :mod:`mpd.models.step` (eager, compiled or captured: one step body),
``_run_steps`` (the loop: validation, progress) and :class:`Checkpointer` (``last.pt``, trunk snapshots,
``meta.json`` and ``model.pt``). With ``data_parallel`` > 1 the loop runs on that many processes
(:mod:`mpd.models.data_parallel`; the other ranks run :func:`follow`).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import hashlib
import json
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

from mpd import locks
from mpd.device import Arithmetic, default_device, resolve, synchronize, training_request
from mpd.models import data_parallel as dp
from mpd.models.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    KINDS,
    LAST_FILE,
    META_FILE,
    MODEL_FILE,
    build_network,
    checkpoint_meta,
    read_checkpoint,
    save_atomic,
)
from mpd.models.compiled_step import CompiledStep, compile_by_default, compile_supported
from mpd.models.context import EE_GOAL, UNNORMALIZED_KEYS
from mpd.models.cuda_graph import GraphedStep
from mpd.models.data import SPLIT_TRAIN, SPLIT_VAL, TrainingArrays, fit_normalizers
from mpd.models.diffusion import sampler_grid
from mpd.models.normalizer import Normalizer
from mpd.models.step import EagerStep, TrainingStep, apply_ema
from mpd.paths import cache_dir
from mpd.provenance import cpu_model, provenance
from mpd.schema import ConfigError, stable_hash, to_dict
from mpd.tasks.spec import ModelSpec, TrainingSpec

VAL_MAX_SAMPLES = 4096  # validation loss on (at most) the first this many val samples, fixed t and noise
LOG_EVERY = 50  # steps between progress-bar updates (each one synchronizes the device)
# Bumped whenever the networks or their losses change, so that a checkpoint of an older architecture is never
# reused under a new one (2: context MLPs with n_layers + 1 hidden layers, the authors' CVAE layout and loss).
NETWORK_VERSION = 2


# TrainingSpec fields added after NETWORK_VERSION 2: they enter a model's identity only when they differ from their
# defaults, so that the models trained before they existed keep their identity (and their cache folder)
LATER_TRAINING_FIELDS = (
    "decay_fraction", "loss_weighting", "min_snr_gamma", "precision", "t_sampling", "t_grid_fraction",
    "goal_row_weight", "kl_warmup_steps", "min_start_goal_distance",
)  # fmt: skip


def training_identity(ts: TrainingSpec, kind: str = "diffusion") -> dict[str, Any]:
    """The training spec as it enters a model's identity (see LATER_TRAINING_FIELDS). ``goal_row_weight`` is an
    option of the diffusion loss: a CVAE's identity never carries it; ``kl_warmup_steps`` one of the CVAE's loss,
    which a diffusion model's never carries."""
    if kind != "diffusion":
        ts = dataclasses.replace(ts, goal_row_weight=1.0)
    else:
        ts = dataclasses.replace(ts, kl_warmup_steps=0)
    d = to_dict(ts)
    defaults = to_dict(TrainingSpec(batch_size=ts.batch_size, steps=ts.steps))
    for name in LATER_TRAINING_FIELDS:
        if d[name] == defaults[name]:
            del d[name]
    return d


def network_identity(spec: ModelSpec, kind: str = "diffusion") -> dict[str, Any]:
    """The network spec as it enters a model's identity: ``goal_head_width`` and ``context_init`` (added after
    NETWORK_VERSION 2) only where a diffusion model departs from their defaults, so the models before them keep
    their identity; a CVAE uses neither."""
    d = to_dict(spec)
    defaults = to_dict(ModelSpec())
    for name in ("goal_head_width", "context_init"):
        if kind != "diffusion" or d[name] == defaults[name]:
            del d[name]
    return d


def model_identity(
    dataset_hash: str,
    kind: str,
    parametrization: str,
    parametrization_settings: dict[str, Any],
    model_spec: ModelSpec,
    training_spec: TrainingSpec,
    seed: int,
    init_from: dict[str, Any] | None = None,
) -> str:
    """The model's identity; ``init_from`` (:func:`init_origin`): the weights a training started from instead of
    its seed's initialization, which enter the identity only where given (the other models keep theirs)."""
    parts = [
        dataset_hash, kind, parametrization, parametrization_settings, network_identity(model_spec, kind),
        training_identity(training_spec, kind), seed, {"network_version": NETWORK_VERSION},
    ]  # fmt: skip
    if init_from is not None:
        parts.append({"init_from": init_from})
    return stable_hash(*parts)


def trunk_identity(
    dataset_hash: str,
    kind: str,
    parametrization: str,
    parametrization_settings: dict[str, Any],
    model_spec: ModelSpec,
    training_spec: TrainingSpec,
    seed: int,
) -> str:
    """The identity of the stable phase of a ``wsd`` training: everything of the model's identity but the number of
    steps and the decay fraction, which only act after the stable phase. Two wsd models of the same trunk are in the
    same state at every step before either one's decay starts."""
    ts = to_dict(training_identity(training_spec, kind))
    ts["steps"] = ts["decay_fraction"] = None
    return stable_hash(
        "trunk", dataset_hash, kind, parametrization, parametrization_settings, network_identity(model_spec, kind), ts,
        seed,
        {"network_version": NETWORK_VERSION},
    )  # fmt: skip


def stable_steps(ts: TrainingSpec) -> int:
    """Steps before a ``wsd`` run's decay starts (the whole run for the other schedules)."""
    if ts.lr_schedule != "wsd":
        return ts.steps
    return ts.steps - round(ts.decay_fraction * ts.steps)


def models_root(cache: str | Path | None = None) -> Path:
    return Path(cache) / "models" if cache is not None else cache_dir() / "models"


def model_dir(task_name: str, kind: str, parametrization: str, identity: str, cache: str | Path | None = None) -> Path:
    return models_root(cache) / task_name / f"{kind}-{parametrization}-{identity}"


# --- state -----------------------------------------------------------------------------------------------
@dataclass
class _Data:
    x: torch.Tensor
    context: dict[str, torch.Tensor]

    def batch(self, idx: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return self.x[idx], {k: v[idx] for k, v in self.context.items()}

    def __len__(self) -> int:
        return int(self.x.shape[0])


def training_indices(arrays: TrainingArrays, ts: TrainingSpec) -> np.ndarray:
    """The samples a training draws from: the training split, less the contexts whose start and goal are closer than
    ``ts.min_start_goal_distance`` (joint-space goals only; raises ValueError naming the field otherwise)."""
    idx = arrays.indices(SPLIT_TRAIN)
    d = ts.min_start_goal_distance
    if d <= 0:
        return idx
    if "q_goal" not in arrays.context:
        raise ValueError(
            f"training.min_start_goal_distance = {d!r}: {arrays.task_name} has an end-effector goal, not a joint "
            "configuration to measure the distance to; use 0"
        )
    gap = np.linalg.norm(arrays.context["q_goal"][idx] - arrays.context["q_start"][idx], axis=-1)
    return idx[gap >= d]


def _to_device(
    arrays: TrainingArrays,
    idx: np.ndarray,
    x_norm: Normalizer,
    ctx_norms: dict[str, Normalizer],
    device: torch.device,
) -> _Data:
    x = x_norm.normalize(torch.as_tensor(arrays.x[idx], dtype=torch.float32, device=device))
    ctx = {}
    for k, v in arrays.context.items():
        t = torch.as_tensor(v[idx], dtype=torch.float32, device=device)
        ctx[k] = t if k in UNNORMALIZED_KEYS else ctx_norms[k].normalize(t)
    return _Data(x, ctx)


def _training_data(
    arrays: TrainingArrays, ts: TrainingSpec, device: torch.device
) -> tuple[_Data, Normalizer, dict[str, Normalizer]]:
    """The training rows on ``device``, normalized, and the normalizers fitted to the data (every rank's alike)."""
    x_norm, ctx_norms = fit_normalizers(arrays)
    return _to_device(arrays, training_indices(arrays, ts), x_norm, ctx_norms, device), x_norm, ctx_norms


@torch.no_grad()
def training_loss_kwargs(kind: str, ts: TrainingSpec, device: torch.device) -> dict[str, Any]:
    """The keywords of ``net.loss`` a training of ``ts`` passes (the diffusion loss's options; none for the CVAE)."""
    if kind != "diffusion":
        return {}
    kw: dict[str, Any] = {
        "weighting": ts.loss_weighting, "min_snr_gamma": ts.min_snr_gamma, "goal_row_weight": ts.goal_row_weight,
    }  # fmt: skip
    if ts.t_sampling == "sampler":
        kw.update(t_grid=sampler_grid().to(device), t_grid_fraction=ts.t_grid_fraction)
    return kw


def _val_loss(net: nn.Module, data: _Data, batch_size: int, seed: int) -> float:
    """Mean loss over the validation samples, with the same t and noise every time (a seeded generator)."""
    g = torch.Generator(device=data.x.device).manual_seed(seed + 1)
    total, n = 0.0, len(data)
    for start in range(0, n, batch_size):
        idx = torch.arange(start, min(start + batch_size, n), device=data.x.device)
        xb, cb = data.batch(idx)
        total += float(net.loss(xb, cb, g)) * len(idx)
    return total / n


def _init_network(kind: str, arrays: TrainingArrays, spec: ModelSpec, seed: int) -> nn.Module:
    # fork_rng: seed the initialization without touching the caller's global RNG state
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return build_network(kind, arrays.dof, arrays.horizon, arrays.context_kind, spec)


def _base_record(
    arrays: TrainingArrays,
    kind: str,
    identity: str,
    model_spec: ModelSpec,
    training_spec: TrainingSpec,
    seed: int,
    x_norm: Normalizer,
    ctx_norms: dict[str, Normalizer],
) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": kind,
        "identity": identity,
        "model_spec": to_dict(model_spec),
        "training_spec": to_dict(training_spec),
        "seed": seed,
        "dof": arrays.dof,
        "horizon": arrays.horizon,
        "context_kind": arrays.context_kind,
        "task_name": arrays.task_name,
        "task_hash": arrays.task_hash,
        "dataset_hash": arrays.dataset_hash,
        "parametrization": arrays.parametrization,
        "parametrization_settings": to_dict(arrays.parametrization_settings),
        "normalizers": {"x": x_norm.to_dict(), "context": {k: n.to_dict() for k, n in ctx_norms.items()}},
        "provenance": provenance(),
    }


@contextlib.contextmanager
def _deferred_sigint() -> Iterator[Callable[[], bool]]:
    """While training, SIGINT only sets a flag (read through the yielded callable): a KeyboardInterrupt raised
    in the middle of an optimizer step would leave a state that cannot be resumed exactly."""
    hit = [False]
    if threading.current_thread() is not threading.main_thread():  # signals go to the main thread only
        yield lambda: False
        return

    def handler(signum: int, frame: object) -> None:
        hit[0] = True

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield lambda: hit[0]
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)


def _write_json_atomic(obj: Any, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=2, sort_keys=True))
    os.replace(tmp, path)


def _latest_trunk_state(trunk_dir: Path, trunk_key: str, stable_end: int, device: torch.device) -> dict | None:
    """The training state of the latest stable-phase snapshot of this trunk at or before ``stable_end`` (None when
    there is none). A snapshot that does not read back, or is of another trunk, is skipped (and named)."""
    if not trunk_dir.is_dir():
        return None
    snaps = sorted(
        (int(p.stem.split("-")[1]), p) for p in trunk_dir.glob("step-*.pt") if p.stem.split("-")[1].isdigit()
    )
    for s, p in reversed(snaps):
        if s > stable_end:
            continue
        try:
            state = read_checkpoint(p, map_location=device)
        except ConfigError as e:
            tqdm.write(f"skipping trunk snapshot {p}: {e}")
            continue
        if state.get("trunk") != trunk_key or int(state["step"]) != s:
            tqdm.write(f"skipping trunk snapshot {p}: it is not step {s} of trunk {trunk_key}")
            continue
        return state
    return None


def check_training_spec(ts: TrainingSpec) -> None:
    """Values the trainer cannot use raise ValueError naming the field."""
    checks = {
        "lr_schedule": ts.lr_schedule in ("constant", "cosine", "wsd"),
        "decay_fraction": 0.0 <= ts.decay_fraction <= 1.0,
        "loss_weighting": ts.loss_weighting in ("uniform", "min_snr"),
        "min_snr_gamma": ts.min_snr_gamma > 0,
        "t_sampling": ts.t_sampling in ("uniform", "sampler"),
        "t_grid_fraction": 0.0 <= ts.t_grid_fraction <= 1.0,
        "precision": ts.precision in ("fp32", "bf16"),
        "goal_row_weight": ts.goal_row_weight > 0,
        "lr_min_ratio": 0.0 <= ts.lr_min_ratio <= 1.0,
        "ema_decay": 0.0 <= ts.ema_decay < 1.0,
        "ema_every": ts.ema_every >= 1,
        "val_every": ts.val_every >= 1,
        "checkpoint_every": ts.checkpoint_every >= 1,
        "warmup_steps": ts.warmup_steps >= 0,
        "kl_warmup_steps": ts.kl_warmup_steps >= 0,
        "min_start_goal_distance": math.isfinite(ts.min_start_goal_distance) and ts.min_start_goal_distance >= 0,
    }
    bad = [k for k, ok in checks.items() if not ok]
    if bad:
        raise ValueError(f"training.{bad[0]} = {getattr(ts, bad[0])!r} is not allowed")


# --- the parts of a training ------------------------------------------------------------------------------
def _checked_spec(
    arrays: TrainingArrays, kind: str, model_spec: ModelSpec, training_spec: TrainingSpec
) -> TrainingSpec:
    """The training spec as the trainer runs it, after the checks of the arguments (raised before any work): the
    other kind's loss options reset to their defaults (neither used nor carried in the identity)."""
    if kind not in KINDS:
        raise ValueError(f"unknown model kind {kind!r} (known: {', '.join(KINDS)})")
    if not isinstance(model_spec, ModelSpec) or not isinstance(training_spec, TrainingSpec):
        raise TypeError("model_spec must be a ModelSpec and training_spec a TrainingSpec")
    if training_spec.steps < 1 or training_spec.batch_size < 1:
        raise ValueError(f"training needs steps >= 1 and batch_size >= 1, got {training_spec}")
    check_training_spec(training_spec)
    arrays.validate()
    if training_spec.min_start_goal_distance > 0:
        n = len(training_indices(arrays, training_spec))
        if n == 0:
            raise ValueError(
                f"training.min_start_goal_distance = {training_spec.min_start_goal_distance!r}: no training context "
                f"of {arrays.task_name} has its start and goal that far apart"
            )
    if kind != "diffusion":  # a diffusion-loss option: the CVAE neither uses it nor carries it in its identity
        return dataclasses.replace(training_spec, goal_row_weight=1.0)
    ts = dataclasses.replace(training_spec, kl_warmup_steps=0)  # and the other way round: a CVAE-loss option
    if ts.goal_row_weight != 1.0 and arrays.context_kind != EE_GOAL:
        raise ValueError(
            f"training.goal_row_weight = {ts.goal_row_weight!r}: {arrays.task_name} has a joint-space goal, so "
            "the model has no free final configuration to weight; use 1"
        )
    return ts


@dataclass
class _Claim:
    """A model to train: its identity, its folder, and this process's lock on it (released when closed or let go)."""

    identity: str
    out: Path
    held: Any

    @property
    def last_path(self) -> Path:
        return self.out / LAST_FILE


def _find_or_claim(
    arrays: TrainingArrays,
    kind: str,
    model_spec: ModelSpec,
    ts: TrainingSpec,
    seed: int,
    cache: str | Path | None,
    shipped: bool,
    init_from: dict[str, Any] | None = None,
) -> Path | _Claim:
    """The ``model.pt`` of this identity when it exists or a shipped prior installs it, else the claim to train it."""
    identity = model_identity(
        arrays.dataset_hash, kind, arrays.parametrization, arrays.parametrization_settings, model_spec, ts, seed,
        init_from,
    )  # fmt: skip
    out = model_dir(arrays.task_name, kind, arrays.parametrization, identity, cache)
    final_path, last_path = out / MODEL_FILE, out / LAST_FILE
    if final_path.is_file():
        return final_path
    # One process per identity: a second `mpd train` (or run) of this model waits here for the first and then finds
    # its model.pt instead of training it again. The lock is released when `held` is closed (when the training
    # returns, or when the process dies: a kill -9 leaves no stale lock).
    held = locks.hold(out)
    if final_path.is_file():
        held.close()
        return final_path
    if shipped and not last_path.is_file():
        from mpd.models import shipped as shipped_priors

        got = shipped_priors.install(arrays.task_name, kind, arrays.parametrization, identity, out)
        if got is not None:
            return got
    out.mkdir(parents=True, exist_ok=True)
    return _Claim(identity, out, held)


@dataclass
class _Trunk:
    """The stable phase of a ``wsd`` training, shared by every budget of it: its key and its snapshots' folder."""

    key: str
    dir: Path
    stable_end: int

    @classmethod
    def of(
        cls, arrays: TrainingArrays, kind: str, model_spec: ModelSpec, ts: TrainingSpec, seed: int, cache: Any
    ) -> _Trunk | None:
        if ts.lr_schedule != "wsd":
            return None
        key = trunk_identity(
            arrays.dataset_hash, kind, arrays.parametrization, arrays.parametrization_settings, model_spec, ts, seed
        )
        folder = models_root(cache) / arrays.task_name / "trunks" / f"{kind}-{arrays.parametrization}-{key}"
        return cls(key, folder, stable_steps(ts))


@dataclass
class TrainingState:
    """What a training carries from step to step and its ``last.pt`` holds: network, EMA, optimizer, the generator
    of every draw, the step count, the wall time of the calls before this one, the validation history and the
    training-loss sum since the last validation (``running``, a 0-d tensor only ever changed in place)."""

    net: nn.Module
    ema: nn.Module
    opt: torch.optim.Optimizer
    gen: torch.Generator
    running: torch.Tensor
    step: int = 0
    wall: float = 0.0
    history: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    running_n: int = 0

    @classmethod
    def fresh(
        cls, kind: str, arrays: TrainingArrays, spec: ModelSpec, ts: TrainingSpec, seed: int, device: torch.device
    ) -> TrainingState:
        net = _init_network(kind, arrays, spec, seed).to(device)
        ema = copy.deepcopy(net).requires_grad_(False)
        opt = make_optimizer(net, ts)
        gen = torch.Generator(device=device).manual_seed(seed)
        return cls(net, ema, opt, gen, torch.zeros((), device=device))

    def load(self, state: dict[str, Any], device: torch.device) -> None:
        """Continue from a checkpoint's training state (a ``last.pt`` or a trunk snapshot)."""
        self.net.load_state_dict(state["weights"])
        self.ema.load_state_dict(state["ema_weights"])
        self.opt.load_state_dict(state["optimizer"])
        self.gen.set_state(state["rng"].cpu())
        self.step, self.wall, self.history = int(state["step"]), float(state["wall_time_s"]), list(state["history"])
        self.running, self.running_n = state["running_loss"].to(device), int(state["running_n"])

    def checkpoint(self, wall: float) -> dict[str, Any]:
        return {
            "weights": self.net.state_dict(),
            "ema_weights": self.ema.state_dict(),
            "optimizer": self.opt.state_dict(),
            "rng": self.gen.get_state(),
            "step": self.step,
            "wall_time_s": wall,
            "history": self.history,
            "running_loss": self.running,
            "running_n": self.running_n,
        }


# the fields of a checkpoint that must equal this training's for its state to be one of this training's states
# (mpd train --from); the training spec is compared apart (every field but the budget's)
SAME_TRAINING_FIELDS = ("kind", "dataset_hash", "parametrization", "parametrization_settings", "model_spec", "seed")
# the fields a checkpoint must share with a training that starts from its weights (mpd train --init-from)
SAME_NETWORK_FIELDS = ("kind", "dataset_hash", "parametrization", "parametrization_settings", "model_spec")
# training-spec fields that do not act on the state: the budget (steps; decay_fraction acts only after the stable
# phase) and how often the loop validates and saves
BUDGET_FIELDS = ("steps", "decay_fraction", "val_every", "checkpoint_every")
# the schedules whose learning rate before a decay is the warm-up then lr, and the fields that act only in the decay:
# a constant run and a wsd run of the same other fields take the same steps up to the wsd run's decay
FLAT_SCHEDULES = {"constant", "wsd"}
DECAY_FIELDS = ("lr_schedule", "lr_min_ratio")


def _stable_end_of(training_spec: dict[str, Any]) -> int:
    """The last step of a recorded training spec's stable phase (its whole run for the constant schedule)."""
    ts = dict(training_spec)
    if ts.get("lr_schedule") != "wsd":
        return int(ts["steps"])
    return int(ts["steps"]) - round(float(ts["decay_fraction"]) * int(ts["steps"]))


def start_state(path: str | Path, record: dict[str, Any], ts: TrainingSpec, device: torch.device) -> dict[str, Any]:
    """The training state of a checkpoint of another budget of this very training (``mpd train --from``): a
    ``last.pt`` (or a copy of one) of the same task data, network, seed and training spec but for the number of
    steps, at a step this training also passes through with the same learning rates. Under the ``constant``
    schedule every step qualifies (a budget of N steps is the first N steps of a longer one, bit for bit); under
    ``wsd`` the steps of both runs' stable phases (as the trunk snapshots, which are made automatically), and a
    constant run's steps up to a wsd run's decay (its stable phase is that run, bit for bit) or the reverse; the
    ``cosine`` schedule's learning rate depends on the budget at every step, so it has no such states. Anything else
    raises :class:`ConfigError` naming the file and the field."""
    state = read_checkpoint(path, map_location=device)
    if ts.lr_schedule == "cosine":
        raise ConfigError(
            path, "training_spec.lr_schedule", "cosine: its learning rate depends on the budget at every step, so no "
            "other budget passes through this training's states (constant and wsd can start from one)",
        )  # fmt: skip
    for name in (*SAME_TRAINING_FIELDS, "init_from"):  # init_from: only in a continued training's record
        if state.get(name) != record.get(name):
            raise ConfigError(path, name, f"is {state.get(name)!r}, this training's is {record.get(name)!r}")
    theirs, ours = dict(state.get("training_spec") or {}), dict(record["training_spec"])
    ignore = set(BUDGET_FIELDS)
    if {theirs.get("lr_schedule"), ours.get("lr_schedule")} <= FLAT_SCHEDULES:
        ignore.update(DECAY_FIELDS)  # a constant run is a wsd run's stable phase, step for step, and vice versa
    differ = sorted(k for k in theirs.keys() | ours.keys() if k not in ignore and theirs.get(k) != ours.get(k))
    if differ:
        detail = ", ".join(f"{k} = {theirs.get(k)!r} (this training: {ours.get(k)!r})" for k in differ)
        raise ConfigError(path, "training_spec", f"differs in more than the budget: {detail}")
    step, ours_end, theirs_end = int(state["step"]), stable_steps(ts), _stable_end_of(theirs)
    if step > ours_end:
        raise ConfigError(
            path, "step", f"is {step}, past this training's {ts.steps} steps (stable phase to {ours_end})"
        )
    if step > theirs_end:
        raise ConfigError(path, "step", f"is {step}, in its own run's decay (its stable phase ends at {theirs_end})")
    return state


def init_origin(
    path: str | Path, arrays: TrainingArrays, kind: str, model_spec: ModelSpec, device: torch.device
) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The EMA weights of a checkpoint (a ``model.pt``, a shipped prior, a ``last.pt`` or a copy of one) for a
    training to start from instead of its seed's initialization (``mpd train --init-from``), and where they came
    from: the checkpoint's identity and step and the sha256 of the weights, which enter the new model's identity.
    The checkpoint must be of the same kind, dataset, parametrization and network (:class:`ConfigError` naming
    the file and the field otherwise): a training continued from another's weights with a fresh optimizer, e.g.
    across machines that keep no cache, where only the shipped EMA weights travel."""
    state = read_checkpoint(path, map_location=device)
    ours = {
        "kind": kind, "dataset_hash": arrays.dataset_hash, "parametrization": arrays.parametrization,
        "parametrization_settings": to_dict(arrays.parametrization_settings), "model_spec": to_dict(model_spec),
    }  # fmt: skip
    for name in SAME_NETWORK_FIELDS:
        if state.get(name) != ours[name]:
            raise ConfigError(path, name, f"is {state.get(name)!r}, this training's is {ours[name]!r}")
    ema = {k: v.float() for k, v in state["ema_weights"].items()}
    digest = hashlib.sha256()
    for k in sorted(ema):
        digest.update(k.encode())
        digest.update(ema[k].cpu().contiguous().numpy().tobytes())
    origin = {"identity": state["identity"], "step": int(state["step"]), "ema_sha256": digest.hexdigest()}
    return origin, ema


def _resume_state(
    claim: _Claim, trunk: _Trunk | None, device: torch.device, start: tuple[Path, dict[str, Any]] | None = None
) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """The checkpoint a training continues from: its own ``last.pt``, else the checkpoint of another budget it was
    told to start from (``start``: the path and its state, :func:`start_state`), else (``wsd``) the latest snapshot
    of its trunk, else none (a fresh start); and the record's fields saying where it first started from, if not at
    step 0 (``resumed_from_trunk_step``, ``started_from``)."""
    if claim.last_path.is_file():
        state = read_checkpoint(claim.last_path, map_location=device)
        if state["identity"] != claim.identity:
            raise ConfigError(
                claim.last_path, "identity", f"is {state['identity']!r}, expected {claim.identity!r} (foreign file)"
            )
        return state, {k: state[k] for k in ("resumed_from_trunk_step", "started_from") if state.get(k) is not None}
    if start is not None:
        path, state = start
        origin = {"identity": state["identity"], "step": int(state["step"]), "file": Path(path).name}
        return state, {"started_from": origin}
    if trunk is not None:
        state = _latest_trunk_state(trunk.dir, trunk.key, trunk.stable_end, device)
        if state is not None:
            return state, {"resumed_from_trunk_step": int(state["step"])}
    return None, {}


class Checkpointer:
    """Writes a training's files: ``last.pt`` every ``checkpoint_every`` steps (and when interrupted or stopped),
    the stable-phase snapshots of a ``wsd`` trunk, and at the end ``meta.json`` then ``model.pt`` (which replaces
    ``last.pt``). Every file carries ``record`` (what made the model); the wall time counts from its creation."""

    def __init__(self, out: Path, record: dict[str, Any], ts: TrainingSpec, trunk: _Trunk | None):
        self.out, self.record, self.ts, self.trunk = out, record, ts, trunk
        self.last_path = out / LAST_FILE
        self.t0 = time.perf_counter()  # the wall time of this call counts from here

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def save(self, state: TrainingState, path: Path | None = None) -> None:
        save_atomic({**self.record, **state.checkpoint(state.wall + self.elapsed())}, path or self.last_path)

    def after_step(self, state: TrainingState) -> None:
        step, ts, trunk = state.step, self.ts, self.trunk
        if step % ts.checkpoint_every == 0 and step < ts.steps:
            self.save(state)
        if (
            trunk is not None
            and step <= trunk.stable_end
            and (step % ts.checkpoint_every == 0 or step == trunk.stable_end)
        ):
            snap = trunk.dir / f"step-{step:09d}.pt"
            if not snap.is_file():  # a stable-phase state: every wsd budget of this trunk passes through it
                trunk.dir.mkdir(parents=True, exist_ok=True)
                self.save(state, snap)

    def finish(self, state: TrainingState, elapsed: float, **meta_fields: Any) -> Path:
        """Write the final model (weights, EMA, history; no optimizer) with its meta; return ``model.pt``'s path."""
        final = {
            **self.record,
            "weights": state.net.state_dict(),
            "ema_weights": state.ema.state_dict(),
            "step": state.step,
            "wall_time_s": state.wall + elapsed,
            "history": state.history,
        }
        meta = checkpoint_meta(final)
        meta.update(meta_fields, created=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        # meta first: a model.pt (what marks a finished model) always has its meta.json
        _write_json_atomic(meta, self.out / META_FILE)
        final_path = self.out / MODEL_FILE
        save_atomic(final, final_path)
        self.last_path.unlink(missing_ok=True)  # the final file supersedes it (a longer run is another identity)
        return final_path


def _execution_mode(
    kind: str,
    device: torch.device,
    arithmetic: Arithmetic,
    cuda_graph: bool | None,
    compile_step: bool | None,
    n_steps: int,
    retrain_shipped: Callable[[], bool],
) -> str:
    """How this call runs its steps: ``cuda_graph``, ``compiled`` or ``eager`` (see :func:`train_model`).
    ``retrain_shipped()``: whether the training retrains a shipped prior that was trained eagerly."""
    if cuda_graph is None:
        cuda_graph = kind == "diffusion" and arithmetic.cuda_graph
    elif cuda_graph and not (kind == "diffusion" and device.type == "cuda"):
        raise ValueError(f"cuda_graph=True: only a diffusion training on CUDA is captured, not {kind} on {device}")
    if compile_step is None:
        compile_step = not cuda_graph and compile_by_default(kind, device, n_steps)
        if compile_step and retrain_shipped():
            compile_step = False  # a shipped prior retrained: its own (eager) execution, for the same bits
    elif compile_step and not compile_supported(kind, device):
        raise ValueError(
            f"compile_step=True: only a diffusion training on a CPU with a C++ compiler, not {kind} on {device}"
        )
    if cuda_graph:
        return "cuda_graph"
    return "compiled" if compile_step else "eager"


def _execution_record(state: dict[str, Any] | None, step: int, mode: str) -> list[list[Any]]:
    """The modes the checkpoint's steps ran in, ``[[first step, mode], ...]``, with this call's appended."""
    execution = [list(e) for e in state.get("execution", [[0, "eager"]])] if state is not None else [[step, mode]]
    if execution[-1][1] != mode:
        execution.append([step, mode])
    return execution


def _record_execution(record: dict[str, Any], mode: str, execution: list[list[Any]], device: torch.device) -> None:
    """What of the execution a model's files record: the modes other than eager where used (the records of the eager
    trainings are as before), and on a CPU the intra-op thread count."""
    if mode == "cuda_graph":
        record["cuda_graph"] = True
    if any(m != "eager" for _, m in execution):
        record["execution"] = execution
    if device.type == "cpu":
        # a CPU training's bits depend on its intra-op thread count too (the reductions' split): the same identity
        # gives the same weights on the same CPU type with the same count (mpd.experiments.artifacts trains with 1)
        record["cpu_threads"] = torch.get_num_threads()


def _make_step(
    mode: str,
    kind: str,
    state: TrainingState,
    ts: TrainingSpec,
    loss_kwargs: dict[str, Any],
    arithmetic: Arithmetic,
    train: _Data,
    shard: dp.Shard | None = None,
) -> TrainingStep:
    """The step object of ``mode``: its batches drawn from ``train`` with the training's generator (``shard``: this
    rank's part of each, in a data-parallel training)."""
    n_train, gen, device = len(train), state.gen, state.running.device

    def draw() -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return train.batch(torch.randint(n_train, (ts.batch_size,), generator=gen, device=device))

    cls = {"cuda_graph": GraphedStep, "compiled": CompiledStep, "eager": EagerStep}[mode]
    return cls(kind, state.net, state.ema, state.opt, gen, ts, loss_kwargs, arithmetic, draw, state.running, shard)


def _run_steps(
    step_fn: TrainingStep,
    state: TrainingState,
    ts: TrainingSpec,
    end: int,
    val: _Data,
    seed: int,
    checkpointer: Checkpointer,
    bar: tqdm,
    any_rank: Callable[[bool], bool] | None = None,
) -> None:
    """Steps up to ``end``: each one, then the validation loss (of the EMA) every ``val_every`` steps and at the
    last, the progress bar, the checkpoints. Ctrl-C stops between two whole steps after saving ``last.pt``; in a
    data-parallel training (``any_rank``: whether a flag holds on any rank) every rank stops after the same step."""
    last_train = last_val = float("nan")
    with _deferred_sigint() as interrupted:
        while state.step < end:
            step_fn(state.step, learning_rate(ts, state.step))
            state.step += 1
            state.running_n += 1
            step = state.step
            if step % ts.val_every == 0 or step == ts.steps:
                last_train = float(state.running) / state.running_n
                state.running.zero_()  # in place: the step object adds to this very tensor
                state.running_n = 0
                if len(val):
                    last_val = _val_loss(state.ema, val, 4 * ts.batch_size, seed)
                state.history.append(
                    {"step": step, "train_loss": last_train, "val_loss": last_val if len(val) else None}
                )
            elif step % LOG_EVERY == 0 or step == end:
                last_train = float(state.running) / state.running_n
            if step % LOG_EVERY == 0 or step == end:
                bar.set_postfix(loss=f"{last_train:.4f}", val=f"{last_val:.4f}", refresh=False)
                bar.update(step - bar.n)
            checkpointer.after_step(state)
            stop = interrupted() if any_rank is None else any_rank(interrupted())
            if stop:  # Ctrl-C: stop between two whole steps, so the resume is exact
                checkpointer.save(state)
                bar.close()
                raise KeyboardInterrupt(f"training interrupted at step {step}; {checkpointer.last_path} resumes it")


# --- public API ------------------------------------------------------------------------------------------
def train_model(
    arrays: TrainingArrays,
    kind: str,
    model_spec: ModelSpec,
    training_spec: TrainingSpec,
    seed: int = 0,
    device: torch.device | str | None = None,
    progress: bool = True,
    cache: str | Path | None = None,
    stop_after: int | None = None,
    shipped: bool = True,
    cuda_graph: bool | None = None,
    compile_step: bool | None = None,
    start_from: str | Path | None = None,
    data_parallel: int = 1,
    init_from: str | Path | None = None,
) -> Path:
    """Train (or find) the model of this identity; return the path of its ``model.pt``.

    Returns at once when ``model.pt`` exists; resumes from ``last.pt`` when a previous run was interrupted
    (Ctrl-C saves ``last.pt`` before re-raising). ``cache`` is the root holding ``models/`` (default
    :func:`mpd.paths.cache_dir`). ``stop_after``: train at most this many steps in this call, save ``last.pt``
    and return *its* path (time-sliced training; used by the resume test). ``shipped``: take the model from the
    shipped priors (:mod:`mpd.models.shipped`, verified by hash) when one has this identity; False trains it.
    ``cuda_graph``: capture the training step in a CUDA graph (:mod:`mpd.models.cuda_graph`; an execution mode, not
    part of the identity); None: where supported (a diffusion model on CUDA, unless ``MPD_CUDA_GRAPH=0``).
    ``compile_step``: the CPU step with the loss compiled by torch.compile (:mod:`mpd.models.compiled_step`, also an
    execution mode); None: a diffusion training on a CPU of at least ``compiled_step.MIN_STEPS`` steps in this call
    (``MPD_TRAIN_COMPILE=0`` never, ``=1`` whatever the length), except the retraining of a shipped prior that was
    trained eagerly (``shipped=False``), which stays eager so that it reproduces the shipped weights bit for bit.
    The modes a checkpoint's steps ran in are recorded as ``execution`` (``[[first step, mode], ...]``) wherever a
    mode other than eager was used. ``start_from``: a checkpoint of another budget of this training to start from
    instead of step 0 (:func:`start_state` says which qualify; the model records it as ``started_from``); its own
    ``last.pt``, when there is one, still comes first. ``data_parallel``: run the steps on this many processes of
    this machine, each on a slice of every batch (:mod:`mpd.models.data_parallel`; a diffusion training on a CPU; an
    execution mode, recorded as ``<mode>/<ranks>``). ``init_from``: a checkpoint whose EMA weights this training
    starts from, as its weights and its EMA, with a fresh optimizer and the step count at 0 (:func:`init_origin`;
    part of the identity, recorded as ``init_from``); its draws come from ``seed`` as a fresh training's do (the
    batches the continued run drew at its start: i.i.d. draws, so no harm; another ``seed`` gives others).
    """
    ts = _checked_spec(arrays, kind, model_spec, training_spec)
    device = torch.device(device) if device is not None else default_device()
    dp.check(kind, device, ts.batch_size, data_parallel)
    origin, init_weights = init_origin(init_from, arrays, kind, model_spec, device) if init_from else (None, None)
    claim = _find_or_claim(arrays, kind, model_spec, ts, seed, cache, shipped, origin)
    if isinstance(claim, Path):
        return claim
    identity = claim.identity

    train, x_norm, ctx_norms = _training_data(arrays, ts, device)
    val = _to_device(arrays, arrays.indices(SPLIT_VAL)[:VAL_MAX_SAMPLES], x_norm, ctx_norms, device)
    record = _base_record(arrays, kind, identity, model_spec, ts, seed, x_norm, ctx_norms)
    # a continued training (init_from) has no trunk: its stable phase is not the seed's
    trunk = _Trunk.of(arrays, kind, model_spec, ts, seed, cache) if origin is None else None
    record["trunk"] = trunk.key if trunk is not None else None
    if origin is not None:
        record["init_from"] = origin
    state = TrainingState.fresh(kind, arrays, model_spec, ts, seed, device)
    if init_weights is not None:  # replaced below by a resumed state's own weights
        state.net.load_state_dict(init_weights)
        state.ema.load_state_dict(init_weights)
    start = (start_from, start_state(start_from, record, ts, device)) if start_from is not None else None
    resumed, origin = _resume_state(claim, trunk, device, start)
    record.update(origin)
    if resumed is not None:
        state.load(resumed, device)

    end = ts.steps if stop_after is None else min(ts.steps, state.step + max(stop_after, 0))
    first_step = state.step
    bar = tqdm(
        total=ts.steps, initial=state.step, unit="step", disable=not progress, dynamic_ncols=True,
        desc=f"{kind}-{arrays.parametrization} {arrays.task_name} [{identity[:8]}]", mininterval=1.0,
    )  # fmt: skip
    arithmetic = resolve(device, training_request(ts.precision))
    if arithmetic.dtype != ts.precision:
        tqdm.write(
            f"{kind} {arrays.task_name}: precision bf16 trains in fp32 arithmetic here: {device} has no native bf16 "
            "(AVX512_BF16 / AMX); emulated bf16 is ~30x slower (MPD_BF16=emulate forces it)"
        )
    mode = _execution_mode(
        kind, device, arithmetic, cuda_graph, compile_step, end - state.step,
        lambda: not shipped and _shipped_eager(arrays.task_name, kind, arrays.parametrization, identity),
    )  # fmt: skip
    if mode == "compiled" and progress:
        tqdm.write(
            f"{kind} {arrays.task_name}: the training step's loss is compiled on the first step (torch.compile, "
            "1-8 min on a busy 2-core CPU, less from inductor's cache); MPD_TRAIN_COMPILE=0 trains eagerly"
        )
    executed = dp.label(mode, data_parallel)
    execution = _execution_record(resumed, state.step, executed)
    if end == state.step and len(execution) > 1 and execution[-1][0] == state.step:
        execution.pop()  # a call that takes no step (a budget that ends at its checkpoint) adds no mode
    _record_execution(record, executed, execution, device)
    checkpointer = Checkpointer(claim.out, record, ts, trunk)
    loss_kwargs = training_loss_kwargs(kind, ts, device)
    if data_parallel == 1:
        state.net.train()
        step_fn = _make_step(mode, kind, state, ts, loss_kwargs, arithmetic, train)
        _run_steps(step_fn, state, ts, end, val, seed, checkpointer, bar)
    else:
        payload = {
            "state": dp.state_bytes(state.checkpoint(state.wall)), "end": end, "arrays": arrays, "kind": kind,
            "model_spec": model_spec, "ts": ts, "seed": seed, "mode": mode,
        }  # fmt: skip
        n_params = sum(p.numel() for p in state.net.parameters())
        with dp.group(data_parallel, n_params, payload) as link:
            state.net.train()
            shard = dp.Shard(link, ts.batch_size, list(state.net.parameters()))
            step_fn = _make_step(mode, kind, state, ts, loss_kwargs, arithmetic, train, shard)
            _run_steps(step_fn, state, ts, end, val, seed, checkpointer, bar, link.any)
    bar.close()
    synchronize(device)
    if state.step < ts.steps:  # stopped by stop_after
        checkpointer.save(state)
        return claim.last_path

    if ts.steps < ts.ema_start:  # the EMA never started: it is the final weights
        apply_ema(state.ema.parameters(), state.net.parameters(), 1.0)
    elapsed = checkpointer.elapsed()
    history = state.history
    return checkpointer.finish(
        state, elapsed,
        n_train=len(train), n_val=len(val), n_parameters=sum(p.numel() for p in state.net.parameters()),
        device=str(device), cpu=cpu_model(), **arithmetic.record(), source="trained", steps=state.step,
        # this call's throughput; none for a call that takes no step (a budget that ends at its checkpoint)
        steps_per_s=(state.step - first_step) / elapsed if elapsed > 0 and state.step > first_step else None,
        final_train_loss=history[-1]["train_loss"] if history else None,
        final_val_loss=history[-1]["val_loss"] if history else None,
    )  # fmt: skip


class _NoFiles(Checkpointer):
    """A data-parallel follower's checkpointer: rank 0 writes the files."""

    def __init__(self) -> None:
        self.last_path = Path("last.pt (rank 0's)")

    def save(self, state: TrainingState, path: Path | None = None) -> None:
        pass

    def after_step(self, state: TrainingState) -> None:
        pass


def follow(
    link: dp.Link,
    state: bytes,
    end: int,
    arrays: TrainingArrays,
    kind: str,
    model_spec: ModelSpec,
    ts: TrainingSpec,
    seed: int,
    mode: str,
) -> None:
    """Rank ``link.rank`` (> 0) of a data-parallel training whose rank 0 runs :func:`train_model` (``state``: its
    training state, ``end``: its last step): the same data and network, this rank's slice of each batch; no files,
    no validation (rank 0's)."""  # fmt: skip
    device = torch.device("cpu")
    train, _, _ = _training_data(arrays, ts, device)
    ours = TrainingState.fresh(kind, arrays, model_spec, ts, seed, device)
    ours.load(dp.read_state(state), device)
    state = ours
    state.net.train()
    arithmetic = resolve(device, training_request(ts.precision))
    shard = dp.Shard(link, ts.batch_size, list(state.net.parameters()))
    step_fn = _make_step(mode, kind, state, ts, training_loss_kwargs(kind, ts, device), arithmetic, train, shard)
    empty = _Data(train.x[:0], {k: v[:0] for k, v in train.context.items()})
    bar = tqdm(disable=True)
    _run_steps(step_fn, state, ts, end, empty, seed, _NoFiles(), bar, link.any)


def _shipped_eager(task_name: str, kind: str, parametrization: str, identity: str) -> bool:
    """Whether a shipped prior of this identity exists and was trained eagerly throughout (its lock's ``execution``)."""
    from mpd.models import shipped as shipped_priors

    path = shipped_priors.find(task_name, kind, parametrization, identity)
    if path is None:
        return False
    lock, _ = shipped_priors.verify(path)
    return all(m == "eager" for _, m in (lock or {}).get("execution") or [[0, "eager"]])


def list_models(task_name: str | None = None, cache: str | Path | None = None) -> list[dict[str, Any]]:
    """Finished models (folders with ``model.pt`` and ``meta.json``), each meta with ``path`` added."""
    root = models_root(cache)
    if not root.is_dir():
        return []
    pattern = f"{task_name}/*/{META_FILE}" if task_name else f"*/*/{META_FILE}"
    out = []
    for meta_path in sorted(root.glob(pattern)):
        if not (meta_path.parent / MODEL_FILE).is_file():
            continue
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        meta["path"] = str(meta_path.parent / MODEL_FILE)
        out.append(meta)
    return out


def learning_rate(ts: TrainingSpec, step: int) -> float:
    """Learning rate of (0-based) step ``step`` under the spec's schedule."""
    if ts.lr_schedule == "constant" and ts.warmup_steps <= 0:
        return ts.lr
    warm = min(1.0, (step + 1) / ts.warmup_steps) if ts.warmup_steps > 0 else 1.0
    if ts.lr_schedule == "constant":
        return ts.lr * warm
    floor = ts.lr_min_ratio
    if ts.lr_schedule == "wsd":
        start = stable_steps(ts)
        if step < start:
            return ts.lr * warm
        frac = min(1.0, (step - start + 1) / max(ts.steps - start, 1))  # the last step is at the floor
        return ts.lr * warm * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * frac)))
    frac = min(1.0, step / max(ts.steps - 1, 1))
    return ts.lr * warm * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * frac)))


def make_optimizer(net: nn.Module, ts: TrainingSpec) -> torch.optim.Optimizer:
    """AdamW; the fused kernel where there is one (about 5x faster than the per-tensor loop on CPU)."""
    device = next(net.parameters()).device
    fused = device.type in ("cpu", "cuda")
    return torch.optim.AdamW(net.parameters(), lr=ts.lr, weight_decay=ts.weight_decay, fused=fused)


__all__ = [
    "EagerStep", "check_training_spec", "list_models", "make_optimizer", "model_dir", "model_identity",
    "network_identity", "stable_steps", "start_state", "train_model", "training_loss_kwargs", "trunk_identity",
]  # fmt: skip
