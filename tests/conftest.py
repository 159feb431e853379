"""Shared test settings: headless matplotlib, global seeds, the names of the bundled tasks and robots."""

from __future__ import annotations

import os
import random

# figures are written without a display; set before anything imports matplotlib
os.environ.setdefault("MPLBACKEND", "Agg")
# spec runs and the Python API compile the diffusion network by default (~20-60 s per batch size on 2 cores); the
# tests run it eager unless they ask for the compiled one (test_experiments, test_models, test_planners, test_api)
os.environ.setdefault("MPD_COMPILE", "0")

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


@pytest.fixture(autouse=True)
def _seed_globals():
    """Code under test takes explicit seeds; this only makes a stray use of a global generator repeatable."""
    random.seed(0)
    np.random.seed(0)  # noqa: NPY002 - the legacy global state is exactly what is pinned here
    torch.manual_seed(0)
