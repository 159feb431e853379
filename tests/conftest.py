"""Shared test settings: headless matplotlib, global seeds, the names of the bundled tasks and robots."""

from __future__ import annotations

import os
import random

# figures are written without a display; set before anything imports matplotlib
os.environ.setdefault("MPLBACKEND", "Agg")
# spec runs and the Python API compile the diffusion network by default (~20-60 s per batch size on 2 cores); the
# tests run it eager unless they ask for the compiled one (test_experiments, test_models, test_planners, test_api)
os.environ.setdefault("MPD_COMPILE", "0")
# under pytest-xdist (the CI runs `-n 2`) each worker is one of two processes on a 2-core machine: one thread each, for
# torch here and for the subprocesses the tests start (two workers of 2 threads each run many times slower than 1 each)
XDIST_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if XDIST_WORKER:
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

TASKS = (
    "EnvSimple2D-RobotPointMass2D",
    "EnvNarrowPassageDense2D-RobotPointMass2D",
    "EnvPlanar2Link-RobotPlanar2Link",
    "EnvPlanar4Link-RobotPlanar4Link",
    "EnvSpheres3D-RobotPanda",
    "EnvWarehouse-RobotPanda",
)
ROBOTS = ("RobotPointMass2D", "RobotPlanar2Link", "RobotPlanar4Link", "RobotPanda")

if XDIST_WORKER:
    torch.set_num_threads(1)

# the files that start Ray (a local instance or a two-node cluster) run one after the other on one xdist worker
# (`--dist loadgroup`): two Ray instances at once would compete for the machine's two cores and the default ports
RAY_FILES = {"test_executor.py", "test_experiments.py", "test_ray_cluster.py"}


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own hook, which reads the groups into the node ids
def pytest_collection_modifyitems(config, items):
    """Each test file is one xdist group (its module fixtures built once, on one worker); the Ray files are one."""
    if not config.pluginmanager.hasplugin("xdist"):
        return
    for item in items:
        name = item.path.name
        item.add_marker(pytest.mark.xdist_group("ray" if name in RAY_FILES else name))


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids):
    """Under ``--dist loadgroup``, stop if the groups did not reach the node ids a worker collected: pytest 9.2 keeps
    node ids where pytest-xdist 3.8 no longer writes the group (pytest-dev/pytest-xdist#1386), and the files were then
    spread test by test over both workers (module fixtures built twice, Ray files at once) without a word."""
    if node.config.getvalue("dist") == "loadgroup" and ids and not any("@" in i for i in ids):
        import importlib.metadata as md

        pytest.exit(
            f"--dist loadgroup did not group the tests by file (pytest {pytest.__version__}, pytest-xdist "
            f"{md.version('pytest-xdist')}; pytest-dev/pytest-xdist#1386): install pytest<9.2 (pip install -e "
            "'.[dev]') or run with -n 0",
            returncode=4,
        )


@pytest.fixture(scope="module")
def one_thread():
    """torch's intra-op threads at 1 for a module's tests (``pytestmark = pytest.mark.usefixtures("one_thread")``):
    their nets and batches are small, and a second thread only adds contention on a 2-core machine."""
    from mpd.executor import threads

    with threads(1):
        yield


@pytest.fixture(autouse=True)
def _seed_globals():
    """Code under test takes explicit seeds; this only makes a stray use of a global generator repeatable."""
    random.seed(0)
    np.random.seed(0)  # noqa: NPY002 - the legacy global state is exactly what is pinned here
    torch.manual_seed(0)


@pytest.fixture
def bench_tool():
    """A loader of the command-line tools under benchmarks/tools/ (scripts, not a package): ``bench_tool("name")``
    is the module of ``benchmarks/tools/name.py``."""
    import importlib.util
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "benchmarks" / "tools"

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
