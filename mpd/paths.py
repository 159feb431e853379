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


SHIPPED_ENV = "MPD_PRIORS"
SHIPPED_BUNDLED = REPO_ROOT / "mpd" / "priors"


def shipped_roots() -> list[Path]:
    """The folders searched for shipped artifacts (priors, dataset digests), in order: ``$MPD_PRIORS`` (folders
    separated by ``os.pathsep``), then the bundled ``mpd/priors``; ``MPD_PRIORS=none`` turns them off."""
    env = os.environ.get(SHIPPED_ENV)
    if env is not None and env.strip().lower() == "none":
        return []
    extra = [Path(p) for p in env.split(os.pathsep) if p] if env else []
    return [*extra, SHIPPED_BUNDLED]
