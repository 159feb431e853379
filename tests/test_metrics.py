"""Metrics: Vendi against a direct eigenvalue computation, and the per-context metrics on hand-made batches."""

import numpy as np
import pytest
import torch

from mpd.collision import CollisionChecker
from mpd.metrics import METRICS, evaluate, path_length, rotation_angle_deg, smoothness, vendi_score
from mpd.tasks import load_task
from mpd.trajectory import Dense, make_parametrization


def vendi_reference(x: np.ndarray) -> float:
    """Definition (Friedman & Dieng 2023): exp(-sum_i l_i log l_i), l = eigenvalues of K/n, K_ij = exp(-|a-b|^2)."""
    n = len(x)
    f = x.reshape(n, -1)
    K = np.array([[np.exp(-np.sum((a - b) ** 2)) for b in f] for a in f])
    lam = np.linalg.eigvals(K / n).real
    lam = lam[lam > 1e-15]
    return float(np.exp(-np.sum(lam * np.log(lam))))


@pytest.mark.parametrize("scale", [0.05, 0.3, 1.0, 3.0])
def test_vendi_matches_direct_eigenvalues(scale):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 16, 2)) * scale
    assert vendi_score(torch.as_tensor(x)) == pytest.approx(vendi_reference(x), rel=1e-8)


def test_vendi_limits():
    x = torch.zeros(7, 5, 3)
    assert vendi_score(x) == pytest.approx(1.0)
    far = torch.arange(6, dtype=torch.float64)[:, None, None] * 100 * torch.ones(6, 5, 3)
    assert vendi_score(far) == pytest.approx(6.0)
    assert np.isnan(vendi_score(torch.zeros(0, 5, 3)))


def test_path_length_smoothness_angle():
    q = torch.tensor([[[0.0, 0.0], [3.0, 4.0], [3.0, 5.0]]])
    assert path_length(q).item() == pytest.approx(6.0)
    ddq = torch.tensor([[[3.0, 4.0], [0.0, 0.0], [0.0, -2.0]]])
    assert smoothness(ddq).item() == pytest.approx(7.0)
    c, s = np.cos(0.3), np.sin(0.3)
    R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]], dtype=torch.float64)
    assert rotation_angle_deg(torch.eye(3, dtype=torch.float64), R).item() == pytest.approx(np.rad2deg(0.3))


def _dense(task, free, qs, qg):
    p = make_parametrization(task, "bspline")
    B = free.shape[0]
    return p.dense(free, qs.expand(B, -1), qg.expand(B, -1))


def test_evaluate_point_mass():
    task = load_task("EnvSimple2D-RobotPointMass2D")
    chk = CollisionChecker(task)
    qs = torch.tensor([-0.2, -0.9], dtype=torch.float64)
    qg = torch.tensor([-0.2, 0.9], dtype=torch.float64)
    p = make_parametrization(task, "bspline")
    ph = torch.as_tensor(p.param_phases()[p.a_free.argmax(0)], dtype=torch.float64)
    line = qs + ph[:, None] * (qg - qs)  # along x = -0.2: 3.6 cm from the nearest disc
    through = line.clone()
    through[:, 0] = -0.37  # through the disc at (-0.370, -0.123)
    free = torch.stack([line, line, through])
    m, val, best = evaluate(chk, _dense(task, free, qs, qg), q_goal=qg)
    assert set(m) == set(METRICS)
    assert val.valid.tolist() == [True, True, False]
    assert m["success"] == 1.0 and m["fraction_valid"] == pytest.approx(2 / 3)
    assert m["vendi"] == pytest.approx(1.0)  # two identical valid trajectories
    assert m["ee_pos_error"] == pytest.approx(0.0, abs=1e-12)
    assert best in (0, 1)
    m, val, best = evaluate(chk, _dense(task, free[2:], qs, qg), q_goal=qg)
    assert m["success"] == 0.0 and best is None and np.isnan(m["vendi"])


def test_evaluate_velocity_limits_fail_fast_trajectory():
    task = load_task("EnvPlanar2Link-RobotPlanar2Link")
    chk = CollisionChecker(task)
    q = torch.zeros(1, 128, 2, dtype=torch.float64)
    q[..., 0] = torch.linspace(0, 0.01, 128)
    dq = torch.zeros_like(q)
    dq[0, 5, 1] = 3.0  # above the 2.175 rad/s limit
    d = Dense(q, dq * 10.0, torch.zeros_like(q), 10.0)
    m, val, _ = evaluate(chk, d, q_goal=q[0, -1])
    assert not val.vel_ok.item() and m["limit_violation_fraction"] == 1.0
