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


def _line_and_through(task):
    """Free rows of a valid straight line along x = -0.2 (3.6 cm from the nearest disc) and of a path through the
    disc at (-0.370, -0.123), with their start and goal."""
    qs = torch.tensor([-0.2, -0.9], dtype=torch.float64)
    qg = torch.tensor([-0.2, 0.9], dtype=torch.float64)
    p = make_parametrization(task, "bspline")
    ph = torch.as_tensor(p.param_phases()[p.a_free.argmax(0)], dtype=torch.float64)
    line = qs + ph[:, None] * (qg - qs)
    through = line.clone()
    through[:, 0] = -0.37
    return line, through, qs, qg


def test_evaluate_point_mass():
    task = load_task("EnvSimple2D-RobotPointMass2D")
    chk = CollisionChecker(task)
    line, through, qs, qg = _line_and_through(task)
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


def _random_rotation(rng) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=rng).as_matrix()


def test_ee_pose_errors_are_the_authors_se3_log_checked_against_scipy_logm():
    """Translation and rotation parts of log(T_goal T_ee^-1) against the 4x4 matrix logarithm of scipy (an
    independent computation): [[phi^, rho], [0, 0]] = logm(T_goal T_ee^-1)."""
    from scipy.linalg import logm

    from mpd.metrics import ee_pose_errors

    rng = np.random.default_rng(3)
    for _ in range(20):
        Rg, Re = _random_rotation(rng), _random_rotation(rng)
        pg, pe = rng.normal(size=3), rng.normal(size=3)
        Tg, Te = np.eye(4), np.eye(4)
        Tg[:3, :3], Tg[:3, 3], Te[:3, :3], Te[:3, 3] = Rg, pg, Re, pe
        L = np.real(logm(Tg @ np.linalg.inv(Te)))
        rho, phi = L[:3, 3], np.array([L[2, 1], L[0, 2], L[1, 0]])
        t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
        pos, ori, euc = ee_pose_errors(t(pe), t(Re), t(pg), t(Rg))
        assert pos.item() == pytest.approx(np.linalg.norm(rho), rel=1e-7)
        assert ori.item() == pytest.approx(np.rad2deg(np.linalg.norm(phi)), rel=1e-7)
        assert euc.item() == pytest.approx(np.linalg.norm(pe - pg), rel=1e-12)
    # a pure translation: the log error is the Euclidean one; a rotation about the goal frame's origin adds a reach
    # term to the translation part even with the EE exactly at the goal position
    I3 = torch.eye(3, dtype=torch.float64)
    p0, p1 = torch.tensor([0.5, 0.0, 0.3], dtype=torch.float64), torch.tensor([0.5, 0.1, 0.3], dtype=torch.float64)
    pos, ori, euc = ee_pose_errors(p1, I3, p0, I3)
    assert pos.item() == pytest.approx(0.1) and euc.item() == pytest.approx(0.1) and ori.item() == 0.0
    c, s = np.cos(0.2), np.sin(0.2)
    Rz = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]], dtype=torch.float64)
    pos, ori, euc = ee_pose_errors(p0, Rz, p0, I3)
    assert euc.item() == 0.0 and pos.item() > 0.05 and ori.item() == pytest.approx(np.rad2deg(0.2))


def test_evaluate_ee_goal_uses_the_log_error_and_picks_the_best_by_it():
    """Planar4Link with an end-effector goal: two valid trajectories; the reported ee_pos_error is the mean log
    error, the Euclidean one is its own column, and the best trajectory is the one of lowest log error."""
    from mpd.metrics import ee_pose_errors

    task = load_task("EnvPlanar4Link-RobotPlanar4Link")
    chk = CollisionChecker(task)
    lo, hi = task.robot.q_min.double(), task.robot.q_max.double()
    cand = lo + torch.rand(500, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * (hi - lo)
    free = cand[chk.configs(cand).valid]
    qg = free[0]
    # standing still at three other collision-free configurations (valid trajectories), away from the goal pose
    q = free[1:4, None].expand(3, 128, 4).contiguous()
    dense = Dense(q, torch.zeros_like(q), torch.zeros_like(q), 10.0)
    p_goal, r_goal = task.robot.ee_pose(qg)
    m, val, best = evaluate(chk, dense, ee_goal=(p_goal, r_goal))
    p_end, r_end = task.robot.ee_pose(q[:, -1])
    pos, ori, euc = ee_pose_errors(p_end, r_end, p_goal, r_goal)
    ok = val.valid
    assert ok.any()
    assert m["ee_pos_error"] == pytest.approx(float(pos[ok].mean()))
    assert m["ee_pos_error_euclidean"] == pytest.approx(float(euc[ok].mean()))
    assert m["ee_ori_error_deg"] == pytest.approx(float(ori[ok].mean()))
    idx = torch.nonzero(ok).flatten()
    assert best == int(idx[pos[idx].argmin()])


def test_vendi_of_a_single_valid_trajectory_is_missing():
    """The authors record no diversity with fewer than two valid trajectories (1.0 would read as 'no diversity')."""
    task = load_task("EnvSimple2D-RobotPointMass2D")
    chk = CollisionChecker(task)
    line, through, qs, qg = _line_and_through(task)
    m, val, best = evaluate(chk, _dense(task, torch.stack([line, through]), qs, qg), q_goal=qg)
    assert val.valid.tolist() == [True, False] and m["n_valid"] == 1.0
    assert np.isnan(m["vendi"]) and best == 0
