"""Where artifacts live. Everything generated (datasets, checkpoints, grids, runs) goes under the cache directory,
``$MPD_CACHE`` or ``<repo>/.cache`` by default (ignored by git)."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def cache_dir() -> Path:
    p = Path(os.environ.get("MPD_CACHE", REPO_ROOT / ".cache")).expanduser()
    p.mkdir(parents=True, exist_ok=True)
    return p


def runs_dir() -> Path:
    p = Path(os.environ.get("MPD_RUNS", REPO_ROOT / "runs")).expanduser()
    p.mkdir(parents=True, exist_ok=True)
    return p
