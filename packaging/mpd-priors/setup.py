"""Build hook of the mpd-priors wheel: the shipped priors of the point-mass and planar-arm tasks (every task but the
Panda ones, which are mpd-priors-panda), copied from the repository's ``mpd/priors/`` (packaging/priors_build.py).
Built in place from the repository: ``pip wheel packaging/mpd-priors --no-deps -w dist`` (``nox -s wheels``)."""

import sys
from pathlib import Path

from setuptools import setup

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from priors_build import build_py_with_priors, is_panda  # noqa: E402

setup(cmdclass={"build_py": build_py_with_priors("mpd_priors", lambda task: not is_panda(task))})
