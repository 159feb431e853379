"""The tiny dataset definition the end-to-end tests generate (spheres checker, a held-out split), written to a file."""

from __future__ import annotations

import textwrap
from pathlib import Path

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
