"""The build hook both prior distributions share: copies the shipped priors of the repository (``mpd/priors/``: the
checkpoints with their lock files under ``models/<task>/``, the dataset digests under ``<task>/``) of the tasks a
distribution takes into its package. The Panda tasks' priors are one wheel (``mpd-priors-panda``), the others'
another (``mpd-priors``): together they hold every shipped prior, each under PyPI's 100 MB limit on a file."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

from setuptools.command.build_py import build_py

SRC = Path(__file__).resolve().parents[1] / "mpd" / "priors"
PANDA = "-RobotPanda"  # the suffix of the Panda tasks' names


def is_panda(task: str) -> bool:
    return task.endswith(PANDA)


def files(takes: Callable[[str], bool]) -> list[Path]:
    """The files of ``mpd/priors`` (relative to it) of the tasks ``takes`` accepts, and the README."""
    if not (SRC / "models").is_dir():
        raise SystemExit(f"mpd priors: {SRC}/models not found; build from the mpd repository (nox -s wheels)")
    found = sorted(SRC.glob("models/*/*")) + sorted(SRC.glob("*/dataset-*"))
    task_of = {f: f.parent.name for f in found}
    out = [f for f in found if f.suffix in (".pt", ".json", ".npz") and takes(task_of[f])]
    return [f.relative_to(SRC) for f in [*out, SRC / "README.md"]]


def build_py_with_priors(package: str, takes: Callable[[str], bool]) -> type[build_py]:
    """A ``build_py`` that also copies the priors of the tasks ``takes`` accepts into ``package``."""

    class BuildPyWithPriors(build_py):
        def run(self) -> None:
            super().run()
            dest = Path(self.build_lib) / package
            for rel in files(takes):
                (dest / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(SRC / rel, dest / rel)

    return BuildPyWithPriors
