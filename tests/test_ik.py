"""Batched damped-least-squares IK on random reachable poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mpd.robots import get_robot
from mpd.robots.ik import rotation_log, solve_ik

pytestmark = pytest.mark.usefixtures("one_thread")


def _targets(robot, n, seed):
    q = robot.random_q(n, torch.Generator().manual_seed(seed))
    p, r = robot.ee_pose(q)
    return q, p, r


@pytest.mark.parametrize("name", ["RobotPanda", "RobotPlanar4Link"])
def test_reaches_random_reachable_poses(name):
    robot = get_robot(name)
    _, p, r = _targets(robot, 64, 0)
    res = solve_ik(robot, p, r, n_restarts=16, generator=torch.Generator().manual_seed(1))
    assert res.success.float().mean() >= 0.95
    ok = res.success
    # independent check of the returned configurations: FK, scipy rotation distance, limits
    p2, r2 = robot.ee_pose(res.q)
    assert ((p2 - p).norm(dim=-1)[ok] < 5e-3).all()
    ang = Rotation.from_matrix(np.einsum("nji,njk->nik", r2.numpy(), r.numpy())).magnitude()
    assert (ang[ok.numpy()] < math.radians(1.0)).all()
    assert robot.within_limits(res.q).all()
    assert torch.allclose(res.pos_err, (p2 - p).norm(dim=-1))


def test_deterministic_given_generator():
    robot = get_robot("RobotPanda")
    _, p, r = _targets(robot, 8, 2)
    a = solve_ik(robot, p, r, n_restarts=4, generator=torch.Generator().manual_seed(5))
    b = solve_ik(robot, p, r, n_restarts=4, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a.q, b.q) and torch.equal(a.success, b.success)


def test_tolerances_valid_filter_and_reference():
    robot = get_robot("RobotPlanar4Link")
    q_true, p, r = _targets(robot, 16, 3)
    loose = solve_ik(
        robot, p, r, n_restarts=8, generator=torch.Generator().manual_seed(0), pos_tol=0.05, rot_tol_deg=10.0
    )
    assert loose.success.all()
    none_valid = solve_ik(
        robot,
        p,
        r,
        n_restarts=8,
        generator=torch.Generator().manual_seed(0),
        valid=lambda q: torch.zeros(len(q), dtype=torch.bool),
    )
    assert not none_valid.success.any()
    # with a reference configuration the closest successful restart is returned
    near = solve_ik(robot, p, r, n_restarts=8, generator=torch.Generator().manual_seed(0), q_init=q_true, q_ref=q_true)
    assert near.success.all()
    assert ((near.q - q_true).norm(dim=-1) < 0.05).all()


def test_position_only_and_rotation_log():
    robot = get_robot("RobotPanda")
    _, p, _ = _targets(robot, 8, 4)
    res = solve_ik(robot, p, None, n_restarts=4, generator=torch.Generator().manual_seed(0))
    assert res.success.all() and (res.rot_err == 0).all()
    rv = torch.tensor(Rotation.random(100, random_state=0).as_rotvec())
    rv = rv * (torch.rand(100, 1, generator=torch.Generator().manual_seed(0)) * 3.0 / rv.norm(dim=-1, keepdim=True))
    m = torch.tensor(Rotation.from_rotvec(rv.numpy()).as_matrix())
    assert torch.allclose(rotation_log(m), rv, atol=1e-9)
