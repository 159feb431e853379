"""Robots: FK against pytorch-kinematics and the reference values, Jacobians and their products against
autograd and finite differences, dtypes and devices, sphere and self-collision pair counts."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import ROBOTS

from mpd.robots import get_robot, pk_serial_chain

F64 = torch.float64


def _q(robot, n: int, seed: int = 0, dtype=F64) -> torch.Tensor:
    return robot.random_q(n, torch.Generator().manual_seed(seed), dtype=dtype)


def _skew(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(w[..., 0])
    return torch.stack(
        [
            torch.stack([z, -w[..., 2], w[..., 1]], -1),
            torch.stack([w[..., 2], z, -w[..., 0]], -1),
            torch.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def _planar_fk(lengths: list[float], q: torch.Tensor) -> torch.Tensor:
    """Independent FK of a planar arm with revolute z joints: joint positions and the tip, (B, n+1, 2)."""
    angles = torch.cumsum(q, -1)
    steps = torch.stack([torch.cos(angles), torch.sin(angles)], -1) * torch.tensor(lengths, dtype=q.dtype)[:, None]
    return torch.cat([torch.zeros_like(steps[:, :1]), torch.cumsum(steps, 1)], 1)


# ---------------------------------------------------------------------------------------------- counts
@pytest.mark.parametrize(
    "name, dof, spheres, pairs",
    [
        ("RobotPointMass2D", 2, 1, 0),
        ("RobotPlanar2Link", 2, 12, 0),
        ("RobotPlanar4Link", 4, 21, 60),
        ("RobotPanda", 7, 56, 280),
    ],
)
def test_counts(name, dof, spheres, pairs):
    r = get_robot(name)
    assert (r.dof, r.n_spheres, len(r.self_pairs)) == (dof, spheres, pairs)
    assert r.sphere_radii.shape == (spheres,) and (r.sphere_radii > 0).all()
    # pairs index distinct spheres on different links
    links = np.array(r.sphere_links)
    assert all(links[i] != links[j] for i, j in r.self_pairs.tolist())


# ------------------------------------------------------------------------------------ reference values
def test_reference_fk_values():
    panda = get_robot("RobotPanda")
    p, R = panda.ee_pose(torch.zeros(7, dtype=F64))
    # the URDF's numbers are parsed as float32 by pytorch-kinematics: 1e-6, not 1e-9
    torch.testing.assert_close(p, torch.tensor([0.088, 0.0, 0.926], dtype=F64), rtol=0, atol=1e-6)
    s = 0.5**0.5
    torch.testing.assert_close(R, torch.tensor([[s, s, 0], [s, -s, 0], [0, 0, -1.0]], dtype=F64), rtol=0, atol=1e-6)
    p, _ = panda.ee_pose(torch.tensor([0, -0.785, 0, -2.356, 0, 1.571, 0.785], dtype=F64))
    torch.testing.assert_close(p, torch.tensor([0.30702, 0, 0.59027], dtype=F64), rtol=0, atol=6e-6)
    p, _ = get_robot("RobotPlanar2Link").ee_pose(torch.tensor([0.3, -0.5], dtype=F64))
    torch.testing.assert_close(p[:2], torch.tensor([0.485087, -0.000497], dtype=F64), rtol=0, atol=6e-7)
    p, _ = get_robot("RobotPlanar4Link").ee_pose(torch.tensor([0.3, -0.5, 0.2, 1.0], dtype=F64))
    torch.testing.assert_close(p[:2], torch.tensor([0.695141, 0.187664], dtype=F64), rtol=0, atol=6e-7)


@pytest.mark.parametrize("name, lengths", [("RobotPlanar2Link", [0.2, 0.3]), ("RobotPlanar4Link", [0.2] * 4)])
def test_planar_fk_vs_closed_form(name, lengths):
    r = get_robot(name)
    q = _q(r, 500)
    joints = _planar_fk(lengths, q)  # (B, n+1, 2)
    p, R = r.ee_pose(q)
    torch.testing.assert_close(p[:, :2], joints[:, -1], rtol=0, atol=1e-12)
    assert torch.all(p[:, 2] == 0)
    angle = q.sum(-1)
    torch.testing.assert_close(R[:, :2, 0], torch.stack([angle.cos(), angle.sin()], -1), rtol=0, atol=1e-12)
    # sphere centres: link offset along the link's direction from the link's joint
    centres = r.sphere_centres(q)
    for k, sph in enumerate(r.spec.spheres):
        link = int(sph.link.split("_")[1]) - 1
        a = q[:, : link + 1].sum(-1)
        want = joints[:, link] + sph.centre[0] * torch.stack([a.cos(), a.sin()], -1)
        torch.testing.assert_close(centres[:, k], want, rtol=0, atol=1e-12)


def test_point_mass_fk_is_identity():
    r = get_robot("RobotPointMass2D")
    q = _q(r, 100)
    torch.testing.assert_close(r.sphere_centres(q)[:, 0], q, rtol=0, atol=0)
    torch.testing.assert_close(r.ee_pose(q)[0][:, :2], q, rtol=0, atol=0)


# ---------------------------------------------------------------------------------- pytorch-kinematics
@pytest.fixture(scope="module")
def panda_pk():
    r = get_robot("RobotPanda")
    return r, pk_serial_chain(str(r.spec.urdf.resolve()), r.spec.urdf.end_link)


def test_panda_fk_vs_pytorch_kinematics(panda_pk):
    robot, chain = panda_pk
    q = _q(robot, 1000)
    frames = chain.forward_kinematics(q, end_only=False)
    want = []
    for s in robot.spec.spheres:
        T = frames[s.link].get_matrix()
        want.append(T[:, :3, :3] @ torch.tensor(s.centre, dtype=F64) + T[:, :3, 3])
    got = robot.sphere_centres(q)
    torch.testing.assert_close(got, torch.stack(want, 1), rtol=0, atol=1e-6)
    assert (got - torch.stack(want, 1)).abs().max() < 1e-12  # not just within tolerance: the same arithmetic
    T = frames[robot.spec.ee_link].get_matrix()
    p, R = robot.ee_pose(q)
    torch.testing.assert_close(p, T[:, :3, 3], rtol=0, atol=1e-6)
    torch.testing.assert_close(R, T[:, :3, :3], rtol=0, atol=1e-6)


def test_panda_jacobian_vs_pytorch_kinematics(panda_pk):
    robot, chain = panda_pk
    q = _q(robot, 1000, seed=1)
    torch.testing.assert_close(robot.ee_jacobian(q), chain.jacobian(q), rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------- Jacobians
@pytest.mark.parametrize("name", ROBOTS)
def test_ee_jacobian_vs_finite_differences(name):
    r = get_robot(name)
    q = _q(r, 64, seed=2)
    J = r.ee_jacobian(q)
    h = 1e-6
    for j in range(r.dof):
        e = torch.zeros(r.dof, dtype=F64)
        e[j] = h
        (p1, R1), (p0, R0) = r.ee_pose(q + e), r.ee_pose(q - e)
        _, R = r.ee_pose(q)
        torch.testing.assert_close(J[:, :3, j], (p1 - p0) / (2 * h), rtol=0, atol=1e-8)
        W = (R1 - R0) / (2 * h) @ torch.linalg.inv(R)  # dR/dq R^-1 = [w]x (R is orthonormal only to ~1e-8)
        torch.testing.assert_close(
            J[:, 3:, j], torch.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], -1), rtol=0, atol=1e-8
        )


def _reference_fk(robot, q: torch.Tensor):
    """Sphere centres (B, S, 3), EE position (B, 3) and rotation (B, 3, 3) by an FK that autograd can go
    through and that shares no code with mpd.robots.chain: pytorch-kinematics for the Panda, closed forms
    otherwise."""
    B = q.shape[0]
    if robot.name == "RobotPanda":
        chain = pk_serial_chain(str(robot.spec.urdf.resolve()), robot.spec.urdf.end_link)
        frames = chain.forward_kinematics(q, end_only=False)
        pts = []
        for s in robot.spec.spheres:
            T = frames[s.link].get_matrix()
            pts.append(T[:, :3, :3] @ torch.tensor(s.centre, dtype=q.dtype) + T[:, :3, 3])
        T = frames[robot.spec.ee_link].get_matrix()
        return torch.stack(pts, 1), T[:, :3, 3], T[:, :3, :3]
    zero, one = torch.zeros(B, dtype=q.dtype), torch.ones(B, dtype=q.dtype)
    if robot.name == "RobotPointMass2D":
        p = torch.stack([q[:, 0], q[:, 1], zero], -1)
        return p[:, None], p, torch.eye(3, dtype=q.dtype).expand(B, 3, 3)
    lengths = [0.2, 0.3] if robot.dof == 2 else [0.2] * 4
    joints = _planar_fk(lengths, q)
    pts = []
    for s in robot.spec.spheres:
        link = int(s.link.split("_")[1]) - 1
        a = q[:, : link + 1].sum(-1)
        xy = joints[:, link] + s.centre[0] * torch.stack([a.cos(), a.sin()], -1)
        pts.append(torch.cat([xy, zero[:, None]], -1))
    a = q.sum(-1)
    rot = torch.stack(
        [
            torch.stack([a.cos(), -a.sin(), zero], -1),
            torch.stack([a.sin(), a.cos(), zero], -1),
            torch.stack([zero, zero, one], -1),
        ],
        -2,
    )
    return torch.stack(pts, 1), torch.cat([joints[:, -1], zero[:, None]], -1), rot


@pytest.mark.parametrize("name", ROBOTS)
def test_reference_fk_agrees(name):
    r = get_robot(name)
    q = _q(r, 64, seed=7)
    pts, p, R = _reference_fk(r, q)
    kin = r.kinematics(q)
    torch.testing.assert_close(kin.points, pts, rtol=0, atol=1e-12)
    torch.testing.assert_close(kin.ee_pos, p, rtol=0, atol=1e-12)
    torch.testing.assert_close(kin.ee_rot, R, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ROBOTS)
def test_points_vjp_vs_autograd(name):
    r = get_robot(name)
    q = _q(r, 32, seed=3)
    kin = r.kinematics(q)
    g = torch.randn(kin.points.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    qa = q.clone().requires_grad_(True)
    pts, _, _ = _reference_fk(r, qa)
    (auto,) = torch.autograd.grad((pts * g).sum(), qa, retain_graph=True)
    torch.testing.assert_close(r.chain.points_vjp(kin, g), auto, rtol=0, atol=1e-10)
    # the task-space entry point pads 2-D gradients
    g2 = g[..., : r.task_dim].contiguous()
    (auto2,) = torch.autograd.grad((pts[..., : r.task_dim] * g2).sum(), qa)
    torch.testing.assert_close(r.spheres_vjp(kin, g2), auto2, rtol=0, atol=1e-10)


@pytest.mark.parametrize("name", ROBOTS)
def test_ee_vjp_vs_autograd(name):
    """C = g_p . p + <G, R>: dC/dq by autograd, and by ee_vjp with the world-frame rotational gradient
    dC/dw_k = <G, [e_k]x R> (R(w) = exp([w]x) R)."""
    r = get_robot(name)
    gen = torch.Generator().manual_seed(4)
    q = _q(r, 32, seed=4)
    kin = r.kinematics(q)
    g_pos = torch.randn(32, 3, generator=gen, dtype=F64)
    G = torch.randn(32, 3, 3, generator=gen, dtype=F64)
    qa = q.clone().requires_grad_(True)
    _, p, R = _reference_fk(r, qa)
    (auto,) = torch.autograd.grad((g_pos * p).sum() + (G * R).sum(), qa)
    R = kin.ee_rot
    g_rot = torch.stack([(G * (_skew(torch.eye(3, dtype=F64)[k]) @ R)).sum((-1, -2)) for k in range(3)], -1)
    torch.testing.assert_close(r.ee_vjp(kin, g_pos, g_rot), auto, rtol=0, atol=1e-10)


# ------------------------------------------------------------------------------------- dtypes, devices
@pytest.mark.parametrize("name", ROBOTS)
def test_float32_matches_float64(name):
    r = get_robot(name)
    q64 = _q(r, 256, seed=5)
    q32 = q64.float()
    k64, k32 = r.kinematics(q64), r.kinematics(q32)
    assert k32.points.dtype == torch.float32 and k32.ee_rot.dtype == torch.float32
    torch.testing.assert_close(k32.points.double(), k64.points, rtol=0, atol=5e-6)
    torch.testing.assert_close(k32.ee_pos.double(), k64.ee_pos, rtol=0, atol=5e-6)
    torch.testing.assert_close(r.chain.ee_jacobian(k32).double(), r.chain.ee_jacobian(k64), rtol=0, atol=5e-6)
    g = torch.randn(k64.points.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    torch.testing.assert_close(
        r.chain.points_vjp(k32, g.float()).double(), r.chain.points_vjp(k64, g), rtol=0, atol=5e-5
    )


def test_batch_shapes():
    r = get_robot("RobotPanda")
    q = _q(r, 12).reshape(3, 4, 7)
    assert r.sphere_centres(q).shape == (3, 4, 56, 3)
    assert r.ee_pose(q)[1].shape == (3, 4, 3, 3)
    assert r.ee_jacobian(q).shape == (3, 4, 6, 7)
    with pytest.raises(ValueError, match="7 joints"):
        r.kinematics(torch.zeros(2, 6, dtype=F64))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("name", ROBOTS)
def test_cuda_matches_cpu(name):
    r = get_robot(name)
    q = _q(r, 1024, seed=6)
    kc, kg = r.kinematics(q), r.kinematics(q.cuda())
    assert kg.points.device.type == "cuda"
    torch.testing.assert_close(kg.points.cpu(), kc.points, rtol=0, atol=1e-12)
    torch.testing.assert_close(r.chain.ee_jacobian(kg).cpu(), r.chain.ee_jacobian(kc), rtol=0, atol=1e-12)
    g = torch.randn(kc.points.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    torch.testing.assert_close(r.chain.points_vjp(kg, g.cuda()).cpu(), r.chain.points_vjp(kc, g), rtol=0, atol=1e-10)
    k32 = r.kinematics(q.float().cuda())
    torch.testing.assert_close(k32.points.double().cpu(), kc.points, rtol=0, atol=5e-6)


def test_limits_and_sampling():
    r = get_robot("RobotPanda")
    q = _q(r, 10_000)
    assert r.within_limits(q).all()
    assert not r.within_limits(q + torch.where(torch.arange(7) == 3, 3.2, 0.0).to(F64)).any()  # joint 4 < 0
    torch.testing.assert_close(r.q_min[3], torch.tensor(-3.0718, dtype=F64))
    a = _q(r, 5, seed=9)
    torch.testing.assert_close(a, _q(r, 5, seed=9), rtol=0, atol=0)


def test_exact_products_and_solve_match_blas():
    """The fixed-order products, solve and functions of ``mpd.robots.exact`` (the data path's, the same bits on
    every CPU) compute what torch's MKL-backed ones do, to rounding."""
    from mpd.robots import exact

    g = torch.Generator().manual_seed(0)
    a, b = (
        torch.randn(5, 4, 3, 6, generator=g, dtype=torch.float64),
        torch.randn(4, 6, 2, generator=g, dtype=torch.float64),
    )
    torch.testing.assert_close(exact.mm(a, b), a @ b, rtol=1e-13, atol=1e-13)
    J = torch.randn(50, 6, 7, generator=g, dtype=torch.float64)
    A = J @ J.transpose(-1, -2) + 0.05**2 * torch.eye(6, dtype=torch.float64)
    y = torch.randn(50, 6, generator=g, dtype=torch.float64)
    torch.testing.assert_close(exact.spd_solve(A, y), torch.linalg.solve(A, y), rtol=1e-10, atol=1e-10)
    x = torch.rand(1000, generator=g, dtype=torch.float64) * 20 - 10
    for name in ("sin", "cos"):
        torch.testing.assert_close(getattr(exact, name)(x), getattr(torch, name)(x), rtol=0, atol=4e-16)
    torch.testing.assert_close(exact.sqrt(x.abs()), x.abs().sqrt(), rtol=4e-16, atol=0)
    # the FK in that arithmetic: the same poses and sphere centres as the BLAS one
    for name in ("RobotPanda", "RobotPlanar4Link"):
        r = get_robot(name)
        q = r.random_q(300, torch.Generator().manual_seed(1), dtype=torch.float64)
        fast, ex = r.kinematics(q), r.kinematics(q, exact=True)
        for f in ("ee_pos", "ee_rot", "points", "axes", "origins"):
            torch.testing.assert_close(getattr(ex, f), getattr(fast, f), rtol=0, atol=1e-14)
