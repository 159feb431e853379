"""Training of the diffusion prior and of the CVAE baseline: cached by identity, resumable, repeatable.

A model's identity is ``stable_hash(dataset_hash, kind, parametrization, parametrization_settings, model spec,
training spec, seed)``; it lives in ``<cache>/models/<task>/<kind>-<parametrization>-<identity>/`` with
``model.pt`` (final), ``last.pt`` (while training, for resuming) and ``meta.json``. Optimizer: AdamW with
gradient-norm clipping; EMA of the weights (kept equal to the weights before ``ema_start``); i.i.d.
minibatches drawn with replacement. Every random number comes from one generator seeded with ``seed``
(network init from ``seed`` too), and its state is checkpointed, so an interrupted and resumed run ends with
the same weights as an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
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
from mpd.device import default_device, synchronize, training_arithmetic
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
from mpd.models.cuda_graph import GraphedStep, graph_supported
from mpd.models.data import SPLIT_TRAIN, SPLIT_VAL, TrainingArrays, fit_normalizers
from mpd.models.diffusion import sampler_grid
from mpd.models.normalizer import Normalizer
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
    "goal_row_weight", "kl_warmup_steps",
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
) -> str:
    return stable_hash(
        dataset_hash,
        kind,
        parametrization,
        parametrization_settings,
        network_identity(model_spec, kind),
        training_identity(training_spec, kind),
        seed,
        {"network_version": NETWORK_VERSION},
    )


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


@torch.no_grad()
def _ema_update(ema: nn.Module, model: nn.Module, decay: float, copy_weights: bool) -> None:
    for pe, pm in zip(ema.parameters(), model.parameters()):
        if copy_weights:
            pe.copy_(pm)
        else:
            pe.lerp_(pm, 1.0 - decay)


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


class EagerStep:
    """``step(xb, cb, s, lr)`` runs (0-based) training step ``s`` on the batch ``(xb, cb)`` eagerly and returns the
    detached loss: loss (under bf16 autocast when ``bf16``), backward, gradient clipping, AdamW at ``lr``, EMA. The
    reference of the other execution modes (:class:`mpd.models.compiled_step.CompiledStep`, the CUDA graph)."""

    def __init__(
        self,
        kind: str,
        net: nn.Module,
        ema: nn.Module,
        opt: torch.optim.Optimizer,
        gen: torch.Generator,
        ts: TrainingSpec,
        loss_kwargs: dict[str, Any],
        bf16: bool,
    ):
        self.kind, self.net, self.ema, self.opt, self.gen, self.ts = kind, net, ema, opt, gen, ts
        self.loss_kwargs = loss_kwargs
        device = next(net.parameters()).device
        self.autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)

    def __call__(self, xb: torch.Tensor, cb: dict[str, torch.Tensor], step: int, lr: float) -> torch.Tensor:
        ts, net, opt = self.ts, self.net, self.opt
        if self.kind == "cvae" and ts.kl_warmup_steps > 0:
            self.loss_kwargs["kl_scale"] = min(1.0, step / ts.kl_warmup_steps)
        with self.autocast:
            loss = net.loss(xb, cb, self.gen, **self.loss_kwargs)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if ts.grad_clip_norm > 0:
            nn.utils.clip_grad_norm_(net.parameters(), ts.grad_clip_norm)
        for g in opt.param_groups:
            g["lr"] = lr
        opt.step()
        if (step + 1) % ts.ema_every == 0:
            _ema_update(self.ema, net, ts.ema_decay, copy_weights=step + 1 < ts.ema_start)
        return loss.detach()


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
    }
    bad = [k for k, ok in checks.items() if not ok]
    if bad:
        raise ValueError(f"training.{bad[0]} = {getattr(ts, bad[0])!r} is not allowed")


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
    mode other than eager was used.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown model kind {kind!r} (known: {', '.join(KINDS)})")
    if not isinstance(model_spec, ModelSpec) or not isinstance(training_spec, TrainingSpec):
        raise TypeError("model_spec must be a ModelSpec and training_spec a TrainingSpec")
    if training_spec.steps < 1 or training_spec.batch_size < 1:
        raise ValueError(f"training needs steps >= 1 and batch_size >= 1, got {training_spec}")
    check_training_spec(training_spec)
    arrays.validate()
    ts = training_spec
    if kind != "diffusion":  # a diffusion-loss option: the CVAE neither uses it nor carries it in its identity
        ts = dataclasses.replace(ts, goal_row_weight=1.0)
    else:  # and the other way round: a CVAE-loss option
        ts = dataclasses.replace(ts, kl_warmup_steps=0)
        if ts.goal_row_weight != 1.0 and arrays.context_kind != EE_GOAL:
            raise ValueError(
                f"training.goal_row_weight = {ts.goal_row_weight!r}: {arrays.task_name} has a joint-space goal, so "
                "the model has no free final configuration to weight; use 1"
            )
    identity = model_identity(
        arrays.dataset_hash,
        kind,
        arrays.parametrization,
        arrays.parametrization_settings,
        model_spec,
        ts,
        seed,
    )
    out = model_dir(arrays.task_name, kind, arrays.parametrization, identity, cache)
    final_path, last_path = out / MODEL_FILE, out / LAST_FILE
    if final_path.is_file():
        return final_path
    # One process per identity: a second `mpd train` (or run) of this model waits here for the first and then finds
    # its model.pt instead of training it again. The lock is released when `held` is closed (on return, or when the
    # process dies: a kill -9 leaves no stale lock).
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
    device = torch.device(device) if device is not None else default_device()

    x_norm, ctx_norms = fit_normalizers(arrays)
    train = _to_device(arrays, arrays.indices(SPLIT_TRAIN), x_norm, ctx_norms, device)
    val = _to_device(arrays, arrays.indices(SPLIT_VAL)[:VAL_MAX_SAMPLES], x_norm, ctx_norms, device)
    record = _base_record(arrays, kind, identity, model_spec, ts, seed, x_norm, ctx_norms)

    net = _init_network(kind, arrays, model_spec, seed).to(device)
    ema = copy.deepcopy(net).requires_grad_(False)
    opt = make_optimizer(net, ts)
    gen = torch.Generator(device=device).manual_seed(seed)
    step, wall, history = 0, 0.0, []
    running, running_n = torch.zeros((), device=device), 0  # training-loss sum since the last validation
    trunk_dir = trunk_key = None
    stable_end = stable_steps(ts)
    if ts.lr_schedule == "wsd":
        trunk_key = trunk_identity(
            arrays.dataset_hash, kind, arrays.parametrization, arrays.parametrization_settings, model_spec, ts, seed
        )
        trunk_dir = models_root(cache) / arrays.task_name / "trunks" / f"{kind}-{arrays.parametrization}-{trunk_key}"
    record["trunk"] = trunk_key
    state = None
    if last_path.is_file():
        state = read_checkpoint(last_path, map_location=device)
        if state["identity"] != identity:
            raise ConfigError(last_path, "identity", f"is {state['identity']!r}, expected {identity!r} (foreign file)")
        if "resumed_from_trunk_step" in state:
            record["resumed_from_trunk_step"] = state["resumed_from_trunk_step"]
    elif trunk_dir is not None:
        state = _latest_trunk_state(trunk_dir, trunk_key, stable_end, device)
        if state is not None:
            record["resumed_from_trunk_step"] = int(state["step"])
    if state is not None:
        net.load_state_dict(state["weights"])
        ema.load_state_dict(state["ema_weights"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["rng"].cpu())
        step, wall, history = int(state["step"]), float(state["wall_time_s"]), list(state["history"])
        running, running_n = state["running_loss"].to(device), int(state["running_n"])

    def save_last(path: Path = last_path) -> None:
        save_atomic(
            {
                **record,
                "weights": net.state_dict(),
                "ema_weights": ema.state_dict(),
                "optimizer": opt.state_dict(),
                "rng": gen.get_state(),
                "step": step,
                "wall_time_s": wall + (time.perf_counter() - t0),
                "history": history,
                "running_loss": running,
                "running_n": running_n,
            },
            path,
        )

    end = ts.steps if stop_after is None else min(ts.steps, step + max(stop_after, 0))
    n_train = len(train)
    first_step = step
    last_train = last_val = float("nan")
    bar = tqdm(
        total=ts.steps, initial=step, unit="step", disable=not progress, dynamic_ncols=True,
        desc=f"{kind}-{arrays.parametrization} {arrays.task_name} [{identity[:8]}]", mininterval=1.0,
    )  # fmt: skip
    loss_kwargs = training_loss_kwargs(kind, ts, device)
    arithmetic = training_arithmetic(ts.precision, device)
    if arithmetic != ts.precision:
        tqdm.write(
            f"{kind} {arrays.task_name}: precision bf16 trains in fp32 arithmetic here: {device} has no native bf16 "
            "(AVX512_BF16 / AMX); emulated bf16 is ~30x slower (MPD_BF16=emulate forces it)"
        )
    if cuda_graph is None:
        cuda_graph = graph_supported(kind, device)
    elif cuda_graph and not (kind == "diffusion" and device.type == "cuda"):
        raise ValueError(f"cuda_graph=True: only a diffusion training on CUDA is captured, not {kind} on {device}")
    if compile_step is None:
        compile_step = not cuda_graph and compile_by_default(kind, device, end - step)
        if compile_step and not shipped and _shipped_eager(arrays.task_name, kind, arrays.parametrization, identity):
            compile_step = False  # a shipped prior retrained: its own (eager) execution, for the same bits
    elif compile_step and not compile_supported(kind, device):
        raise ValueError(
            f"compile_step=True: only a diffusion training on a CPU with a C++ compiler, not {kind} on {device}"
        )
    graphed = compiled = None
    if compile_step:
        compiled = CompiledStep(net, ema, opt, gen, ts, loss_kwargs, arithmetic == "bf16")
        if progress:
            tqdm.write(
                f"{kind} {arrays.task_name}: the training step's loss is compiled on the first step (torch.compile, "
                "1-8 min on a busy 2-core CPU, less from inductor's cache); MPD_TRAIN_COMPILE=0 trains eagerly"
            )
    stepper = compiled or EagerStep(kind, net, ema, opt, gen, ts, loss_kwargs, arithmetic == "bf16")
    if cuda_graph:
        graphed = GraphedStep(
            net, ema, opt,
            lambda: train.batch(torch.randint(n_train, (ts.batch_size,), generator=gen, device=device)),
            gen, ts, loss_kwargs, arithmetic == "bf16", running,
        )  # fmt: skip
        record["cuda_graph"] = True  # recorded where used (the records of the eager trainings are as before)
    mode = "cuda_graph" if graphed is not None else "compiled" if compiled is not None else "eager"
    execution = [list(e) for e in state.get("execution", [[0, "eager"]])] if state is not None else [[step, mode]]
    if execution[-1][1] != mode:
        execution.append([step, mode])
    if any(m != "eager" for _, m in execution):  # recorded where used (the eager trainings' records are as before)
        record["execution"] = execution
    if device.type == "cpu":
        # a CPU training's bits depend on its intra-op thread count too (the reductions' split): the same identity
        # gives the same weights on the same CPU type with the same count (mpd.experiments.artifacts trains with 1)
        record["cpu_threads"] = torch.get_num_threads()
    t0 = time.perf_counter()
    net.train()
    with _deferred_sigint() as interrupted:
        while step < end:
            if graphed is not None:  # the same step, captured: batch, loss, clipping, AdamW, EMA, running sum
                graphed(step, learning_rate(ts, step))
                step += 1
            else:  # eager, or its loss compiled (the same draws, clipping, AdamW and EMA)
                xb, cb = train.batch(torch.randint(n_train, (ts.batch_size,), generator=gen, device=device))
                running += stepper(xb, cb, step, learning_rate(ts, step))
                step += 1
            running_n += 1
            if step % ts.val_every == 0 or step == ts.steps:
                last_train = float(running) / running_n
                running.zero_()  # in place: a captured step adds to this very tensor
                running_n = 0
                if len(val):
                    last_val = _val_loss(ema, val, 4 * ts.batch_size, seed)
                history.append({"step": step, "train_loss": last_train, "val_loss": last_val if len(val) else None})
            elif step % LOG_EVERY == 0 or step == end:
                last_train = float(running) / running_n
            if step % LOG_EVERY == 0 or step == end:
                bar.set_postfix(loss=f"{last_train:.4f}", val=f"{last_val:.4f}", refresh=False)
                bar.update(step - bar.n)
            if step % ts.checkpoint_every == 0 and step < ts.steps:
                save_last()
            if trunk_dir is not None and step <= stable_end and (step % ts.checkpoint_every == 0 or step == stable_end):
                snap = trunk_dir / f"step-{step:09d}.pt"
                if not snap.is_file():  # a stable-phase state: every wsd budget of this trunk passes through it
                    trunk_dir.mkdir(parents=True, exist_ok=True)
                    save_last(snap)
            if interrupted():  # Ctrl-C: stop between two whole steps, so the resume is exact
                save_last()
                bar.close()
                raise KeyboardInterrupt(f"training interrupted at step {step}; {last_path} resumes it")
    bar.close()
    synchronize(device)
    if step < ts.steps:  # stopped by stop_after
        save_last()
        return last_path

    if ts.steps < ts.ema_start:  # the EMA never started: it is the final weights
        _ema_update(ema, net, ts.ema_decay, copy_weights=True)
    elapsed = time.perf_counter() - t0
    wall += elapsed
    final = {
        **record,
        "weights": net.state_dict(),
        "ema_weights": ema.state_dict(),
        "step": step,
        "wall_time_s": wall,
        "history": history,
    }
    meta = checkpoint_meta(final)
    meta.update(
        n_train=n_train,
        n_val=len(val),
        n_parameters=sum(p.numel() for p in net.parameters()),
        device=str(device),
        cpu=cpu_model(),
        arithmetic=arithmetic,
        source="trained",
        steps=step,
        steps_per_s=(step - first_step) / elapsed if elapsed > 0 else None,
        final_train_loss=history[-1]["train_loss"] if history else None,
        final_val_loss=history[-1]["val_loss"] if history else None,
        created=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    )
    # meta first: a model.pt (what marks a finished model) always has its meta.json
    _write_json_atomic(meta, out / META_FILE)
    save_atomic(final, final_path)
    last_path.unlink(missing_ok=True)  # the final file supersedes it (a longer run is another identity)
    return final_path


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


def steps_per_second(net: nn.Module, x: torch.Tensor, context: dict[str, torch.Tensor], n_steps: int = 10) -> float:
    """Training steps/s of ``net`` on one fixed batch (forward, backward, AdamW step); for sizing profiles."""
    opt = make_optimizer(net, TrainingSpec(batch_size=x.shape[0], steps=n_steps))
    g = torch.Generator(device=x.device).manual_seed(0)

    def one() -> None:
        loss = net.loss(x, context, g)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()

    one()
    synchronize(x.device)
    t0 = time.perf_counter()
    for _ in range(n_steps):
        one()
    synchronize(x.device)
    return n_steps / (time.perf_counter() - t0)


__all__ = [
    "EagerStep", "check_training_spec", "list_models", "make_optimizer", "model_dir", "model_identity",
    "network_identity", "stable_steps", "steps_per_second", "train_model", "training_loss_kwargs", "trunk_identity",
]  # fmt: skip
