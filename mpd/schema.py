"""Typed, frozen dataclass configs loaded from TOML with errors that name the file and the field.

Every declarative file of mpd (tasks, robots, dataset definitions, experiment specs) is read through
:func:`from_dict`, so a typo, a missing field or a wrong type always produces one line of the form::

    mpd/tasks/data/X.toml: [trajectory].n_control_points: expected int, got str 'abc'
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """A declarative file is invalid. The message names the file and the field."""

    def __init__(self, source: str | Path | None, where: str, message: str):
        self.source = str(source) if source is not None else "<dict>"
        self.where = where
        self.detail = message
        loc = f"{self.source}: {where}: " if where else f"{self.source}: "
        super().__init__(loc + message)


def read_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(path, "", f"invalid TOML: {e}") from None


def _fmt(where: str, key: str) -> str:
    if not where:
        return key
    return f"{where}.{key}"


def _describe(value: Any) -> str:
    r = repr(value)
    if len(r) > 60:
        r = r[:57] + "..."
    return f"{type(value).__name__} {r}"


def _convert(tp: Any, value: Any, source: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        alternatives = [a for a in args if a is not type(None)]
        if len(alternatives) == 1:  # X | None: X's own error, which names the inner field
            return _convert(alternatives[0], value, source, where)
        for a in alternatives:
            try:
                return _convert(a, value, source, where)
            except ConfigError as e:
                errors.append(e.detail)
        names = " or ".join(_type_name(a) for a in args if a is not type(None))
        raise ConfigError(source, where, f"expected {names}, got {_describe(value)}")
    if origin is typing.Literal:
        if value not in args:
            allowed = ", ".join(repr(a) for a in args)
            raise ConfigError(source, where, f"{value!r} is not one of: {allowed}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, list | tuple):
            raise ConfigError(source, where, f"expected a list, got {_describe(value)}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(source, where, f"expected {len(args)} entries, got {len(value)}")
            return tuple(_convert(a, v, source, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        inner = args[0] if args else Any
        out = [_convert(inner, v, source, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(source, where, f"expected a table, got {_describe(value)}")
        kt, vt = args if args else (Any, Any)
        return {_convert(kt, k, source, where): _convert(vt, v, source, _fmt(where, str(k))) for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, source=source, where=where)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(source, where, f"expected a number, got {_describe(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(source, where, f"expected int, got {_describe(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(source, where, f"expected true/false, got {_describe(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(source, where, f"expected str, got {_describe(value)}")
        return value
    raise TypeError(f"unsupported schema type {tp!r}")


def check_type(tp: Any, value: Any, source: Any = None, where: str = "") -> Any:
    """``value`` converted to the annotation ``tp`` (as :func:`from_dict` does for a field), or a
    :class:`ConfigError` naming ``source`` and ``where``."""
    return _convert(tp, value, source, where)


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    return getattr(tp, "__name__", str(tp))


def from_dict(cls: type[T], data: Any, *, source: str | Path | None = None, where: str = "") -> T:
    """Build the dataclass ``cls`` from a TOML table, checking keys and types recursively."""
    if not isinstance(data, dict):
        raise ConfigError(source, where, f"expected a table, got {_describe(data)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        allowed = ", ".join(sorted(fields))
        raise ConfigError(source, _fmt(where, unknown[0]), f"unknown key (allowed: {allowed})")
    kwargs = {}
    for name, f in fields.items():
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], source, _fmt(where, name))
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(source, _fmt(where, name), "missing required field")
    obj = cls(**kwargs)
    check = getattr(obj, "validate", None)
    if check is not None:
        try:
            check()
        except ConfigError as e:
            if e.source == "<dict>":  # raised by validate() without knowing the file
                raise ConfigError(source, _fmt(where, e.where), e.detail) from None
            raise
        except ValueError as e:
            raise ConfigError(source, where or "", str(e)) from None
    return obj


def to_dict(obj: Any) -> Any:
    """Plain (JSON-able) form of a dataclass tree."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, list | tuple):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): to_dict(v) for k, v in obj.items()}
    return obj


def canonical_json(obj: Any) -> str:
    return json.dumps(to_dict(obj), sort_keys=True, separators=(",", ":"))


def stable_hash(*parts: Any, n: int = 16) -> str:
    """Content hash of JSON-able parts (dataclasses allowed); the identity of every artifact."""
    h = hashlib.sha256()
    for p in parts:
        h.update(canonical_json(p).encode())
        h.update(b"\0")
    return h.hexdigest()[:n]


def file_sha256(path: str | Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()
