"""Where things live. Everything generated (datasets, checkpoints, grids) goes under the cache directory:
``$MPD_CACHE``, else ``<checkout>/.cache`` when mpd runs from a git checkout, else the user's cache folder
(``$XDG_CACHE_HOME/mpd`` or ``~/.cache/mpd``) for an installed wheel. Runs go to ``$MPD_RUNS``, else
``<checkout>/runs``, else ``./runs``.

The experiment specs and dataset definitions live in the checkout (``benchmarks/specs/``, ``datasets/``); a wheel
carries copies of them inside the package (``mpd/_bundled/``, made by ``setup.py`` at build time)."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
# a git checkout (an editable install or running from the source tree), not an installed wheel
IN_CHECKOUT = (REPO_ROOT / "pyproject.toml").is_file() and (REPO_ROOT / "mpd" / "paths.py").is_file()
BUNDLED = Path(__file__).resolve().parent / "_bundled"


def _data_dir(checkout_path: str) -> Path:
    """A folder of the checkout, or its copy in an installed wheel."""
    p = REPO_ROOT / checkout_path
    return p if IN_CHECKOUT or not (BUNDLED / Path(checkout_path).name).is_dir() else BUNDLED / Path(checkout_path).name


SPECS_DIR = _data_dir("benchmarks/specs")
DATASETS_DIR = _data_dir("datasets")


def cache_dir() -> Path:
    if "MPD_CACHE" in os.environ:
        default = Path(os.environ["MPD_CACHE"])
    elif IN_CHECKOUT:
        default = REPO_ROOT / ".cache"
    else:
        default = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mpd"
    p = default.expanduser()
    p.mkdir(parents=True, exist_ok=True)
    return p


def runs_dir() -> Path:
    p = Path(os.environ.get("MPD_RUNS", REPO_ROOT / "runs" if IN_CHECKOUT else Path.cwd() / "runs")).expanduser()
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
    return [*extra, SHIPPED_BUNDLED, *companion_priors()]


def companion_priors() -> list[Path]:
    """The folders of installed prior distributions (the ``mpd-priors`` wheel, built from ``packaging/mpd-priors``):
    the entry points of group ``mpd.priors``, each naming a module whose ``ROOT`` is such a folder."""
    from importlib import import_module
    from importlib.metadata import entry_points

    out = []
    for ep in entry_points(group="mpd.priors"):
        try:
            root = Path(getattr(import_module(ep.module), ep.attr or "ROOT"))
        except (ImportError, AttributeError, TypeError):
            continue
        if root.is_dir() and root not in out:
            out.append(root)
    return out
