"""Build hook: a wheel of mpd carries copies of the experiment specs (``benchmarks/specs/``) and the dataset
definitions with their lock files (``datasets/``) in ``mpd/_bundled/``, so that an installed mpd runs ``mpd run quick``
outside a checkout (``mpd.paths``). The shipped priors are a companion distribution: ``packaging/mpd-priors``."""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
BUNDLE = {
    "specs": (ROOT / "benchmarks" / "specs", ("*.toml",)),
    "datasets": (ROOT / "datasets", ("*.toml", "*.json", "README.md")),
}


class BuildPyWithData(build_py):
    def run(self):
        super().run()
        for name, (src, patterns) in BUNDLE.items():
            dest = Path(self.build_lib) / "mpd" / "_bundled" / name
            dest.mkdir(parents=True, exist_ok=True)
            for pattern in patterns:
                for f in sorted(src.glob(pattern)):
                    shutil.copyfile(f, dest / f.name)


setup(cmdclass={"build_py": BuildPyWithData})
