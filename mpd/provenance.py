"""What made an artifact: code version, git commit and dirty flag, library versions, device."""

from __future__ import annotations

import functools
import platform
import subprocess
from importlib import metadata

from mpd import __version__
from mpd.paths import REPO_ROOT

LIBRARIES = ("torch", "numpy", "scipy", "ompl", "pybullet", "pytorch_kinematics", "rerun-sdk", "pandas")


@functools.lru_cache(maxsize=1)
def git_state() -> tuple[str, bool]:
    """(commit, dirty) of the repository the package runs from; ("unknown", False) outside git."""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
        dirty = bool(
            subprocess.run(
                ["git", "status", "--porcelain", "--untracked-files=no"],
                cwd=REPO_ROOT,
                capture_output=True,
                text=True,
                timeout=5,
                check=True,
            ).stdout.strip()
        )
        return commit, dirty
    except (OSError, subprocess.SubprocessError):
        return "unknown", False


@functools.lru_cache(maxsize=1)
def library_versions() -> dict[str, str]:
    out = {"python": platform.python_version(), "mpd": __version__}
    for name in LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "missing"
    return out


@functools.lru_cache(maxsize=1)
def cpu_model() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo), else the platform's word for it: float rounding in training
    differs between CPU types, so two runs' models may differ for this reason alone."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def provenance() -> dict[str, object]:
    commit, dirty = git_state()
    return {
        "mpd_version": __version__,
        "git_commit": commit,
        "git_dirty": dirty,
        "libraries": library_versions(),
    }
