"""The tiny dataset definition the end-to-end tests generate (spheres checker, a held-out split), written to a file;
experiment specs written from Python values."""

from __future__ import annotations

import json
import re
import textwrap
from pathlib import Path
from typing import Any

TASK = "EnvSimple2D-RobotPointMass2D"


def tiny_definition(
    path: Path, name: str = "tiny", task: str = TASK, n: int = 32, chunk: int = 16, **extra: str
) -> Path:
    """Write a definition of ``n`` contexts in chunks of ``chunk`` to ``path``; ``extra`` replaces a field's value
    with the given TOML text (for bad-field tests)."""
    body = textwrap.dedent(f"""
        name = "{name}"
        task = "{task}"
        n_contexts = {n}
        seed = 0
        chunk_size = {chunk}
        [checker]
        kind = "spheres"
        [split]
        val = 0.3
        test = 0.5
        """)
    for k, v in extra.items():
        body = body.replace(f"\n{k} = ", f"\n{k} = {v}  # ", 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(body)
    return path


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (str, Path)):
        return json.dumps(str(value), ensure_ascii=False)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"no TOML for {value!r}")


def _toml_lines(table: dict[str, Any]) -> list[str]:
    """A table's ``key = value`` lines; a dict of dicts as dotted keys (``models."diffusion-bspline" = { ... }``)."""
    lines = []
    for k, v in table.items():
        if isinstance(v, dict) and v and all(isinstance(x, dict) for x in v.values()):
            lines += [f"{_toml_key(k)}.{_toml_key(sub)} = {_toml_value(x)}" for sub, x in v.items()]
        else:
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    return lines


def write_spec_file(
    path: Path,
    axes: dict[str, Any],
    tasks: dict[str, dict[str, Any]] | None = None,
    after_axes: str = "",
    **top: Any,
) -> Path:
    """Write an experiment spec to ``path``: the ``top`` fields, the ``[axes]`` table, ``after_axes`` (TOML text as
    written: more axes, other tables) and a ``[tasks."NAME"]`` table per entry of ``tasks``."""
    lines = [*_toml_lines(top), "[axes]", *_toml_lines(axes), textwrap.dedent(after_axes).strip()]
    for name, table in (tasks or {}).items():
        lines += [f"[tasks.{_toml_key(name)}]", *_toml_lines(table)]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(line for line in lines if line) + "\n")
    return path
