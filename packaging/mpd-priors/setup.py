"""Build hook of the mpd-priors wheel: copies the shipped priors of the repository (``mpd/priors/``: the checkpoints
with their lock files under ``models/``, the dataset digests under ``<task>/``) into the package. Built in place from
the repository: ``pip wheel packaging/mpd-priors --no-deps -w dist`` (``nox -s wheels``)."""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

SRC = Path(__file__).resolve().parents[2] / "mpd" / "priors"


class BuildPyWithPriors(build_py):
    def run(self):
        super().run()
        if not (SRC / "models").is_dir():
            raise SystemExit(f"mpd-priors: {SRC}/models not found; build from the mpd repository (nox -s wheels)")
        dest = Path(self.build_lib) / "mpd_priors"
        for f in sorted(SRC.glob("models/*/*")) + sorted(SRC.glob("*/dataset-*")) + [SRC / "README.md"]:
            if f.suffix in (".pt", ".json", ".npz", ".md"):
                (dest / f.relative_to(SRC)).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(f, dest / f.relative_to(SRC))


setup(cmdclass={"build_py": BuildPyWithPriors})
