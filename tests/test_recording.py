"""Rerun recordings, read back with ``rerun.chunk.RrdReader``: the entities (environment, robot, samples), the
timelines (``denoising_step`` has one entry per recorded step, ``time`` one per dense point), the Panda's joint
transforms against our forward kinematics, ``rerun rrd verify``, and ``record_run``'s file names."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import defaultdict

import numpy as np
import pytest
import torch

from mpd.tasks import load_task
from mpd.trajectory import make_parametrization
from mpd.viz.recording import STEP, TIME, best_index, record_history, record_run, recording_name

N_POINTS = 128


def fake_history(task_name: str, B: int = 5, S: int = 4, seed: int = 0) -> dict[str, np.ndarray]:
    """S steps of B B-spline trajectories converging on a straight line, as the runner records them."""
    t = load_task(task_name)
    par = make_parametrization(t)
    g = torch.Generator().manual_seed(seed)
    qs, qg = t.robot.random_q(2, g)
    line = qs + torch.as_tensor(par.param_phases())[:, None] * (qg - qs)
    steps = []
    for s in range(S):
        noise = 0.2 * (S - 1 - s) / S + 0.02
        w = line + noise * torch.randn(B, par.n_params, t.dof, generator=g, dtype=torch.float64)
        steps.append(par.dense(par.free_rows(w), qs.expand(B, -1), None if t.ee_goal else qg.expand(B, -1)))
    d = steps[-1]
    assert d.q.shape[1] == N_POINTS
    return {
        "q": d.q.numpy().astype(np.float32),
        "dq": d.dq_dt.numpy().astype(np.float32),
        "ddq": d.ddq_dt2.numpy().astype(np.float32),
        "valid": np.arange(B) % 2 == 0,
        "steps_q": np.stack([s.q.numpy() for s in steps]).astype(np.float32),
        "steps_valid": np.stack([np.arange(B) < s for s in range(S)]),
        "steps_label": np.array(["noise:0"] + [f"denoising:{s}" for s in range(1, S)]),
    }


def read_back(path):
    """(entities, {timeline: set of values}, {entity: [record batches]}) of an .rrd file."""
    from rerun.chunk import RrdReader

    entities, times, batches = set(), defaultdict(set), defaultdict(list)
    for ch in RrdReader(path).stream().to_chunks():
        entities.add(ch.entity_path)
        rb = ch.to_record_batch()
        batches[ch.entity_path].append(rb)
        for tl in ch.timeline_names:
            if tl in (TIME, STEP):
                times[tl].update(rb.column(tl).to_pylist())
    return entities, times, batches


def _verify(path) -> int:
    return subprocess.run(
        [sys.executable, "-m", "rerun_cli", "rrd", "verify", str(path)], capture_output=True, timeout=60
    ).returncode


def _has_default_blueprint(path) -> bool:
    r = subprocess.run(
        [sys.executable, "-m", "rerun_cli", "rrd", "print", "-v", str(path)], capture_output=True, text=True, timeout=60
    )
    out = r.stdout + r.stderr  # rerun prints the store infos and commands on stderr
    return "make_default: true" in out and "/viewport" in out and "ViewBlueprint" in out


@pytest.mark.parametrize("name", ["EnvSimple2D-RobotPointMass2D", "EnvPlanar2Link-RobotPlanar2Link"])
def test_2d_recording(tmp_path, name):
    S = 4
    hist = fake_history(name, S=S)
    path = record_history(tmp_path / "a.rrd", name, {"extra_objects": True, "method": "mpd"}, hist)
    ents, times, _ = read_back(path)
    assert any(e.startswith("/world/environment/obstacles/") for e in ents)
    assert any(e.startswith("/world/environment/extra/") for e in ents)
    assert "/world/samples" in ents and "/world/final/samples" in ents
    robot = {"/world/robot/body"} if "PointMass" in name else {"/world/robot/links", "/world/robot/spheres"}
    assert robot <= ents
    assert len(times[STEP]) == S and len(times[TIME]) == N_POINTS
    assert _verify(path) == 0
    assert _has_default_blueprint(path)


def _quat_matrix(xyzw) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(xyzw).as_matrix()


def test_panda_recording_matches_our_kinematics(tmp_path):
    name = "EnvSpheres3D-RobotPanda"
    S = 3
    hist = fake_history(name, B=4, S=S)
    path = record_history(tmp_path / "p.rrd", name, {"extra_objects": False, "method": "gp-cost"}, hist)
    ents, times, batches = read_back(path)
    assert sum("/visual_geometries/" in e for e in ents) >= 10  # the URDF's meshes (ROS_PACKAGE_PATH set)
    assert {f"/world/robot/joints/panda_joint{i}" for i in range(1, 8)} <= ents
    assert any(e.startswith("/world/environment/obstacles/") for e in ents)
    assert not any(e.startswith("/world/environment/extra/") for e in ents)
    assert "/world/samples" in ents
    assert len(times[STEP]) == S and len(times[TIME]) == N_POINTS

    # the transforms the viewer composes, at one time step, put the hand where our FK does
    k = 70
    edges = {}  # child frame -> (parent frame, 4x4)

    def add(rb, row):
        d = {c: rb.column(c)[row].as_py() for c in rb.schema.names}
        T = np.eye(4)
        T[:3, :3] = _quat_matrix(d["Transform3D:quaternion"][0])
        T[:3, 3] = d["Transform3D:translation"][0]
        edges[d["Transform3D:child_frame"][0]] = (d["Transform3D:parent_frame"][0], T)

    for rb in batches["/tf_static"]:
        for row in range(rb.num_rows):
            add(rb, row)
    for i in range(1, 8):
        (rb,) = [b for b in batches[f"/world/robot/joints/panda_joint{i}"] if TIME in b.schema.names]
        add(rb, k)
    frame, T = "panda_hand", np.eye(4)
    while frame in edges:
        frame, E = edges[frame]
        T = E @ T
    assert frame == "panda_link0"
    robot = load_task(name).robot
    b, _ = best_index(hist["q"], hist["valid"])
    p, R = robot.ee_pose(torch.as_tensor(hist["q"][b, k], dtype=torch.float64))
    np.testing.assert_allclose(T[:3, 3], p.numpy(), atol=2e-5)
    np.testing.assert_allclose(T[:3, :3], R.numpy(), atol=2e-5)
    assert _verify(path) == 0


def test_best_index_is_the_first_valid_shortest():
    q = np.zeros((4, 3, 1))
    q[:, 2, 0] = [3.0, 1.0, 1.0, 0.5]  # lengths 3, 1, 1, 0.5
    assert best_index(q, np.array([True, True, True, False])) == (1, True)
    assert best_index(q, np.zeros(4, bool)) == (3, False)


def test_recording_names():
    cells = [
        {"task": "T", "method": "mpd", "extra_objects": True, "rotation_deg": 0.0, "n_samples": n} for n in (1, 10)
    ] + [{"task": "T", "method": "dprior", "extra_objects": False, "rotation_deg": 20.0, "n_samples": 1}]
    assert recording_name(cells[0], 0, cells) == "T-mpd-extra-n1-ctx0.rrd"
    assert recording_name(cells[2], 3, cells) == "T-dprior-train-rot20-ctx3.rrd"
    assert recording_name(cells[1], 0) == "T-mpd-extra-ctx0.rrd"


def test_record_run_builds_and_skips_up_to_date(tmp_path):
    name = "EnvSimple2D-RobotPointMass2D"
    run = tmp_path / "run"
    (run / "histories").mkdir(parents=True)
    cell = {"task": name, "method": "mpd", "extra_objects": False, "rotation_deg": 0.0, "n_samples": 5}
    (run / "manifest.json").write_text(
        json.dumps({"cells": [{"key": "abc", **cell}, {"key": "def", **cell, "method": "gp-cost"}]})
    )
    hist = fake_history(name, S=2)
    # a history with its row, and one from an older runner (parameters only in the manifest)
    np.savez(run / "histories" / "abc-ctx0.npz", **hist, row_json=np.array(json.dumps({**cell, "cell_key": "abc"})))
    np.savez(run / "histories" / "def-ctx1.npz", **hist)
    out = record_run(run)
    assert [p.name for p in out] == [f"{name}-gp-cost-train-ctx1.rrd", f"{name}-mpd-train-ctx0.rrd"]
    mtimes = [p.stat().st_mtime_ns for p in out]
    assert [p.stat().st_mtime_ns for p in record_run(run)] == mtimes  # newer than the histories: kept
    assert not list((run / "recordings").glob(".*"))  # no temporary file left
