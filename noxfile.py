"""Task runner. Every session shares one virtual environment (``.nox/mpd``), created with the standard library's
``venv`` and pip (uv would ignore the local CPU wheel of torch and download several GB of CUDA builds), and
re-installed only when ``pyproject.toml`` changes: a second ``nox -s demo`` starts in seconds.

    nox -s tests                  unit, property and end-to-end tests (every one: nox -s tests -- -m "slow or not slow")
    nox -s lint                   ruff check and ruff format --check
    nox -s demo                   the quick experiment end to end: dataset, training, every method, recording, report
    nox -s experiments -- SPEC    run an experiment spec (benchmarks/specs/NAME.toml or a path)
    nox -s report -- RUN|SPEC     regenerate a run's figures and tables from its results table
    nox -s view -- RUN [--web]    open the Rerun viewer on a run's recordings
    nox -s benchmarks             pytest-benchmark suites, JSON under .benchmarks/
    nox -s gpu                    the prepared GPU check on a CUDA machine (benchmarks/gpu_check.py): JSON summary
    nox -s gpu_wheels             the wheels the offline GPU machine lacks, for its Python 3.12, into .whl/
    nox -s wheels                 the mpd wheel and the two wheels of the shipped priors into dist/
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
from pathlib import Path

import nox

ROOT = Path(__file__).parent
VENV = ROOT / ".nox" / "mpd"
nox.options.sessions = ["tests"]


def _venv(session: nox.Session, extras: str = "dev,ray,mlflow") -> Path:
    """Create/refresh the shared environment (one set of extras for every session, so that switching sessions never
    reinstalls); returns its bin directory. `nox -s NAME --install-only` creates it and runs nothing else."""
    bin_dir = VENV / ("Scripts" if sys.platform == "win32" else "bin")
    python = bin_dir / "python"
    stamp = VENV / ".mpd-stamp"
    want = hashlib.sha256((ROOT / "pyproject.toml").read_bytes() + extras.encode()).hexdigest()
    if not python.exists():
        session.run_install(sys.executable, "-m", "venv", str(VENV), external=True)
    if not stamp.exists() or stamp.read_text() != want:
        session.run_install(str(python), "-m", "pip", "install", "-q", "--upgrade", "pip", external=True)
        session.run_install(str(python), "-m", "pip", "install", "-q", "-e", f".[{extras}]", external=True)
        stamp.write_text(want)
    session.env["PATH"] = f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"
    session.env["VIRTUAL_ENV"] = str(VENV)
    return bin_dir


@nox.session(venv_backend="none")
def tests(session: nox.Session) -> None:
    """Run the test suite (fast by default; `-- -m slow` for the slow ones), over one pytest-xdist worker per core
    (each pinned to one thread by tests/conftest.py); `-- -n 0` runs it in one process."""
    b = _venv(session)
    args = list(session.posargs or ["-q"])
    if not any(a == "-n" or a.startswith(("-n", "--numprocesses")) or a == "no:xdist" for a in args):
        args = ["-n", "auto", "--dist", "loadgroup", *args]
    session.run(str(b / "python"), "-m", "pytest", *args, external=True)


# reports/: the reports' analysis scripts
LINT_PATHS = ("mpd", "tests", "benchmarks", "reports", "noxfile.py", "setup.py")


@nox.session(venv_backend="none")
def lint(session: nox.Session) -> None:
    """ruff: the lint rules and the formatting (the same checks as .pre-commit-config.yaml)."""
    b = _venv(session)
    session.run(str(b / "ruff"), "check", *LINT_PATHS, external=True)
    session.run(str(b / "ruff"), "format", "--check", *LINT_PATHS, external=True)


@nox.session(venv_backend="none")
def demo(session: nox.Session) -> None:
    """The embedded default: the `quick` spec end to end, then where to find the report and the recording."""
    b = _venv(session)
    # the eager network: compiling it in each worker would cost the demo more than its 48 short plans of the
    # diffusion methods gain (`mpd run quick` outside the demo compiles, as every spec run does by default)
    session.env.setdefault("MPD_COMPILE", "0")
    session.run(str(b / "mpd"), "run", "quick", "--workers", "2", "--report", *session.posargs, external=True)


@nox.session(venv_backend="none")
def experiments(session: nox.Session) -> None:
    """Run an experiment spec: nox -s experiments -- SPEC [mpd run options]."""
    if not session.posargs:
        session.error("usage: nox -s experiments -- SPEC [--only KEY=VALUE ...] [--executor ray] [--workers N]")
    b = _venv(session)
    session.run(str(b / "mpd"), "run", *session.posargs, external=True)


@nox.session(venv_backend="none")
def report(session: nox.Session) -> None:
    """Regenerate figures and tables of a run (or the latest run of a spec) from its results table."""
    if not session.posargs:
        session.error("usage: nox -s report -- RUN_OR_SPEC")
    b = _venv(session)
    session.run(str(b / "mpd"), "report", *session.posargs, external=True)


@nox.session(venv_backend="none")
def view(session: nox.Session) -> None:
    """Open the Rerun viewer on a run's recordings (`--web` serves the web viewer on localhost)."""
    b = _venv(session)
    session.run(str(b / "mpd"), "view", *(session.posargs or ["latest"]), external=True)


@nox.session(venv_backend="none")
def benchmarks(session: nox.Session) -> None:
    """pytest-benchmark suites; results as JSON under .benchmarks/."""
    b = _venv(session)
    out = ROOT / ".benchmarks" / "latest.json"
    out.parent.mkdir(exist_ok=True)
    session.run(
        str(b / "python"),
        "-m",
        "pytest",
        "benchmarks",
        "-m",
        "benchmark",
        "--benchmark-only",
        "--benchmark-enable",
        f"--benchmark-json={out}",
        "-p",
        "no:cacheprovider",
        *session.posargs,
        external=True,
    )


@nox.session(venv_backend="none")
def gpu(session: nox.Session) -> None:
    """The GPU check on a CUDA machine with internet: CUDA tests, plan and network benchmarks on the GPU, a short
    training, one JSON summary (.benchmarks/gpu.json, or the path after --). Installs mpd into the interpreter
    running nox, whose torch must be a CUDA build (the pinned torch from PyPI is one on Linux)."""
    session.run(sys.executable, "-m", "pip", "install", "-q", "-e", f"{ROOT}[dev]", external=True)
    out = session.posargs[0] if session.posargs else str(ROOT / ".benchmarks" / "gpu.json")
    session.run(sys.executable, str(ROOT / "benchmarks" / "gpu_check.py"), "--out", out, external=True)


# what an offline GPU machine's image lacks of mpd's dependencies (its python3 holds torch, numpy, scipy, pandas,
# matplotlib, pytest, ...): pybullet has no wheel for it (its tests skip there), rerun and ray are not needed
GPU_WHEELS = ["ompl==2.0.1", "pytorch_kinematics==0.10.0", "arm_pytorch_utilities", "pytorch_seed"]
# the files of pybullet_data that mpd reads without pybullet (the Panda's kinematics come from its URDF)
GPU_PYBULLET_DATA = ["franka_panda/panda.urdf"]


@nox.session(venv_backend="none")
def gpu_wheels(session: nox.Session) -> None:
    """Download, here, the wheels the offline GPU machine needs (Python 3.12, manylinux x86-64) into .whl/ (ignored by
    git), with the Panda URDF as a pybullet_data package; carry `.whl` to it and run benchmarks/gpu_check.py there as
    its docstring says."""
    dest = ROOT / ".whl"
    platforms = ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"]
    args = ["--no-deps", "--only-binary=:all:", "--python-version", "3.12", "--implementation", "cp"]
    for p in platforms:
        args += ["--platform", p]
    session.run(sys.executable, "-m", "pip", "download", "-q", *args, "-d", str(dest), *GPU_WHEELS, external=True)
    # pybullet_data without pybullet: a package of the URDF files alone, importable with .whl on PYTHONPATH
    src = Path(
        session.run(
            str(_venv(session) / "python"),
            "-c",
            "import pybullet_data; print(pybullet_data.getDataPath())",
            silent=True,
            external=True,
        ).strip()
    )
    pkg = dest / "pybullet_data"
    for rel in GPU_PYBULLET_DATA:
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src / rel, pkg / rel)
    (pkg / "__init__.py").write_text(
        "# pybullet_data's URDF files that mpd reads, unchanged, for a machine without pybullet (noxfile: gpu_wheels)\n"
        "import os\n\n\ndef getDataPath():\n    return os.path.dirname(__file__)\n"
    )


@nox.session(venv_backend="none")
def wheels(session: nox.Session) -> None:
    """The mpd wheel (small: code, task files, specs, dataset definitions) and the companion wheels of the shipped
    priors (mpd-priors: the point-mass and planar-arm tasks', packaging/mpd-priors; mpd-priors-panda: the Panda
    tasks', packaging/mpd-priors-panda) into dist/; install them by name:
    pip install --find-links dist "mpd[priors]"."""
    b = _venv(session)
    out = ROOT / "dist"
    for src in (ROOT, ROOT / "packaging" / "mpd-priors", ROOT / "packaging" / "mpd-priors-panda"):
        session.run(str(b / "python"), "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation", "-w",
                    str(out), external=True)  # fmt: skip
        shutil.rmtree(src / "build", ignore_errors=True)
    for w in sorted(out.glob("*.whl")):
        session.log(f"{w.name}: {w.stat().st_size / 1e6:.1f} MB")
