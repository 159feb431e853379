"""The prepared GPU check (benchmarks/gpu_check.py) runs end to end, here on the CPU, so that the command is known to
work before it runs on a GPU machine: every section present, none failed, the numbers sane."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]


def test_gpu_check_runs_every_section_on_the_cpu(tmp_path):
    out = tmp_path / "gpu.json"
    cmd = [sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--device", "cpu", "--quick", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)  # any folder
    s = json.loads(out.read_text())
    assert proc.returncode == 0 and s["errors"] == [], proc.stderr[-3000:]
    assert s["environment"]["device"] == "cpu" and s["environment"]["torch"] == torch.__version__
    tests = s["cuda_tests"]
    assert tests["failed"] == 0 and tests["passed"] + tests["skipped"] >= 1
    if not torch.cuda.is_available():
        assert tests["passed"] == 0  # the CUDA tests skip on a CPU
    for method in ("mpd", "dprior"):
        plan = s["plans"][f"{method}/EnvSimple2D-RobotPointMass2D"]
        assert plan["median_s"] > 0 and plan["breakdown"]["network"] > 0
    assert s["plans"]["mpd/EnvSimple2D-RobotPointMass2D"]["breakdown"]["cost_gradient_calls"] > 0
    net = s["network"]
    assert net["parameters"] > 1e6 and net["forward_batch100_fp32_ms"] > 0 and net["train_steps_per_s_batch32_bf16"] > 0
    tr = s["training"]
    assert tr["finite"] and tr["loads_on_cpu"] and tr["device_recorded"] == "cpu" and tr["steps"] == 10


def test_gpu_train_rebuilds_the_reversed_copies_as_the_dataset_makes_them():
    """benchmarks/gpu_train.py carries forward paths only and rebuilds the reversed copies there: its rule (start
    three times, free rows, final configuration twice more; reversed) against the B-spline parametrization's own
    free rows of the time-reversed control points (what mpd.data.dataset stores), on random end-effector-goal rows."""
    import numpy as np

    from mpd.tasks import load_task
    from mpd.trajectory import make_parametrization

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import gpu_train

    param = make_parametrization(load_task("EnvSpheres3D-RobotPanda"), "bspline")
    rng = np.random.default_rng(0)
    q_start, free = rng.normal(size=(5, 7)), rng.normal(size=(5, param.n_params - 5, 7))
    full = np.concatenate([np.repeat(q_start[:, None], 3, 1), free, np.repeat(free[:, -1:], 2, 1)], 1)
    assert np.array_equal(param.free_rows(full), free)
    np.testing.assert_array_equal(gpu_train.reversed_rows(free, q_start), param.free_rows(full[:, ::-1]))


def test_gpu_train_brings_the_shipped_file_and_its_lock_to_the_top_of_its_output(tmp_path):
    """A device call brings back its output folder's files only a few levels deep: gpu_train moves the shipped prior
    (`<root>/models/<task>/<file>.pt`, as mpd.models.shipped.ship writes it) and its lock to the output folder
    itself, byte for byte, and leaves nothing behind."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import gpu_train

    folder = tmp_path / "out" / "ship" / "models" / "EnvSimple2D-RobotPointMass2D"
    folder.mkdir(parents=True)
    (folder / "diffusion-bspline-0123456789abcdef.pt").write_bytes(b"weights")
    (folder / "diffusion-bspline-0123456789abcdef.lock.json").write_text("{}")
    moved = gpu_train.flat(folder / "diffusion-bspline-0123456789abcdef.pt", tmp_path / "out")
    assert moved == tmp_path / "out" / "diffusion-bspline-0123456789abcdef.pt" and moved.read_bytes() == b"weights"
    assert (tmp_path / "out" / "diffusion-bspline-0123456789abcdef.lock.json").read_text() == "{}"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "diffusion-bspline-0123456789abcdef.lock.json", "diffusion-bspline-0123456789abcdef.pt",
    ]  # fmt: skip
