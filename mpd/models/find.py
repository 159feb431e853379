"""Find a trained model for a task: a checkpoint path, a model identity (or a prefix of one), the newest one in the
cache, or the task's default shipped prior. What ``mpd plan`` and :func:`mpd.load_planner` use.

The default shipped prior of a (task, kind, parametrization) is the verified shipped prior trained on the most
samples (steps x batch size; the newest on a tie): the longest training the repository ships, e.g. a task's `gpu`
profile over its `cpu` one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mpd.models.checkpoint import LoadedModel, load_model
from mpd.models.shipped import list_shipped
from mpd.models.train import list_models
from mpd.schema import ConfigError
from mpd.trajectory import PARAMETRIZATIONS

# refs that name no particular model
DEFAULT = "default"  # the default shipped prior
LATEST = "latest"  # the newest model of the cache, else the default shipped prior


def _samples(lock: dict[str, Any]) -> int:
    ts = lock.get("training_spec") or {}
    return int(lock.get("steps") or ts.get("steps") or 0) * int(ts.get("batch_size") or 0)


def shipped_priors(task_name: str, kind: str, parametrization: str) -> list[dict[str, Any]]:
    """The verified shipped priors of this task, kind and parametrization, the default first."""
    locks = [
        e
        for e in list_shipped()
        if e["ok"] and e.get("task_name") == task_name and e.get("kind") == kind
        if e.get("parametrization") == parametrization
    ]
    return sorted(locks, key=lambda e: (_samples(e), str(e.get("shipped", ""))), reverse=True)


def resolve_model(
    task_name: str, kind: str, parametrization: str | None, ref: str | Path | None = None
) -> tuple[Path, str]:
    """(checkpoint path, source) of the model ``ref`` names; source is "path", "cache" or "shipped".

    ``ref``: None or ``"default"`` (the default shipped prior), ``"latest"`` (the newest model of the cache, else the
    default shipped prior), a checkpoint path, or a model identity or a prefix of one (the cache first, then the
    shipped priors). ``parametrization`` None: any, for a path or an identity (the model's own), ``"bspline"`` for
    ``"default"`` and ``"latest"``. Raises :class:`ConfigError` naming what was looked for."""
    ref = DEFAULT if ref is None else ref
    if isinstance(ref, Path) or (ref not in (DEFAULT, LATEST) and Path(ref).exists()):
        return Path(ref), "path"
    if parametrization is None:
        if ref in (DEFAULT, LATEST):
            return resolve_model(task_name, kind, "bspline", ref)
        errors = []
        for p in PARAMETRIZATIONS:
            try:
                return resolve_model(task_name, kind, p, ref)
            except ConfigError as e:
                errors.append(e.detail)
        raise ConfigError("model", "", "; ".join(dict.fromkeys(errors)))  # each parametrization's reason, once
    what = f"{kind} model with the {parametrization} parametrization for {task_name}"
    hint = f"train one: mpd train --task {task_name} --model {kind} --parametrization {parametrization}"
    ref = str(ref)
    shipped = shipped_priors(task_name, kind, parametrization)
    if ref == DEFAULT:
        if not shipped:
            raise ConfigError("model", "", f"no shipped {what} ({hint})")
        return Path(shipped[0]["path"]), "shipped"
    cached = [
        m for m in list_models(task_name) if m.get("kind") == kind and m.get("parametrization") == parametrization
    ]
    if ref == LATEST:
        if cached:
            return Path(max(cached, key=lambda m: Path(m["path"]).stat().st_mtime)["path"]), "cache"
        if shipped:
            return Path(shipped[0]["path"]), "shipped"
        raise ConfigError("model", "", f"no trained {what} in the cache and none shipped ({hint})")
    if not ref or any(c not in "0123456789abcdef" for c in ref.lower()):
        raise ConfigError("model", "", f"{ref!r} is neither a checkpoint file nor a model identity (hex digits)")
    hits = [m for m in cached if str(m.get("identity", "")).startswith(ref.lower())]
    if hits:
        return Path(max(hits, key=lambda m: Path(m["path"]).stat().st_mtime)["path"]), "cache"
    hits = [e for e in shipped if str(e.get("identity", "")).startswith(ref.lower())]
    if len({e["identity"] for e in hits}) > 1:
        ids = ", ".join(sorted({e["identity"] for e in hits}))
        raise ConfigError("model", "", f"{ref!r} is a prefix of several shipped models ({ids})")
    if hits:
        return Path(hits[0]["path"]), "shipped"
    known = ", ".join(e["identity"] for e in shipped) or "none"
    raise ConfigError("model", "", f"no {what} of identity {ref!r} in the cache nor shipped (shipped: {known})")


def find_model(
    task_name: str, kind: str, parametrization: str | None, ref: str | Path | None = None, device=None
) -> LoadedModel:
    """The model ``ref`` names (:func:`resolve_model`), loaded for sampling and checked against the task and the
    parametrization (None: the model's own, see :func:`resolve_model`)."""
    path, source = resolve_model(task_name, kind, parametrization, ref)
    model = load_model(path, expect_task=task_name, expect_parametrization=parametrization, device=device)
    if model.kind != kind:
        raise ConfigError("model", "", f"{path} is a {model.kind} model, a {kind} model is needed")
    model.meta.setdefault("source", source)
    return model


__all__ = ["DEFAULT", "LATEST", "find_model", "resolve_model", "shipped_priors"]
