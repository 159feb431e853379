"""The kinematic-chain additions made for the costs: the batch-last FK against the batch-first formulation it
replaced, the frame-based Jacobian product, the reach bound, and the sparse product of ``mpd.costs``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mpd.robots import get_robot

ROBOTS = ("RobotPointMass2D", "RobotPlanar2Link", "RobotPlanar4Link", "RobotPanda")


def batch_first_fk(chain, q: torch.Tensor):
    """The formulation it replaced: frames (B, 3, dof + 1, 4), a (B*3, 3) x (3, 3) product per term."""
    c = chain._c(q.dtype, q.device)
    B = q.shape[0]
    T = q.new_zeros(B, 3, chain.dof + 1, 4)
    T[:, :, 0, :3] = torch.eye(3, dtype=q.dtype)
    R, p = T[:, :, 0, :3].contiguous(), q.new_zeros(B, 3)
    s, co = torch.sin(q), 1 - torch.cos(q)
    axes, origins = [], []
    for j in range(chain.dof):
        ao = R @ c["axis_off"][j]
        o = p + ao[..., 1]
        if chain.revolute[j]:
            rt = c["rot_terms"][j]
            R = torch.addcmul(
                torch.addcmul(R @ rt[:, :3], s[:, j, None, None], R @ rt[:, 3:6]),
                co[:, j, None, None],
                R @ rt[:, 6:],
            )
            axis, p = ao[..., 0], o
        else:
            R = R @ c["off_r"][j]
            axis = R @ c["axes"][j]
            p = o + axis * q[:, j, None]
        T[:, :, j + 1, :3], T[:, :, j + 1, 3] = R, p
        axes.append(axis)
        origins.append(o)
    pts = (T.reshape(B, 3, -1) @ c["wpoints"]).transpose(1, 2)
    Re, pe = T[:, :, chain.ee_joint + 1, :3], T[:, :, chain.ee_joint + 1, 3]
    return torch.stack(axes, 1), torch.stack(origins, 1), pts, pe + Re @ c["ee_p"], Re @ c["ee_r"]


@pytest.mark.parametrize("name", ROBOTS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fk_matches_batch_first_formulation(name, dtype):
    """Same operands, same order of every sum: bit-identical on the 2-core reference CPU; the tolerance only
    leaves room for BLAS kernels that order a 3-term sum differently on other CPUs."""
    r = get_robot(name)
    q = r.random_q(3000, torch.Generator().manual_seed(0), dtype) * 1.2
    kin = r.kinematics(q)
    ref = batch_first_fk(r.chain, q)
    tol = {"rtol": 0, "atol": 1e-6 if dtype == torch.float32 else 1e-14}
    for got, want in zip((kin.axes, kin.origins, kin.points, kin.ee_pos, kin.ee_rot), ref):
        torch.testing.assert_close(got, want, **tol)
    # the public fields are views of the batch-last buffers
    assert kin.points.data_ptr() == kin.points_t.data_ptr()
    assert kin.frames_t is None if r.chain.translational else kin.frames_t.shape == (r.dof + 1, 4, 3, 3000)


@pytest.mark.parametrize("name", ROBOTS)
def test_frame_jacobian_product_and_reach(name):
    r = get_robot(name)
    q = r.random_q(4000, torch.Generator().manual_seed(1))
    kin = r.kinematics(q)
    g = torch.randn(kin.points_t.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    ref = r.chain.points_vjp(kin, g.permute(2, 0, 1))
    torch.testing.assert_close(r.chain.points_vjp_frames(kin, g), ref, rtol=1e-12, atol=1e-12)
    reach = r.chain.reach
    if reach is None:
        assert not r.chain.revolute.all()  # the point mass: prismatic joints, unbounded
    else:
        assert kin.points_t.norm(dim=1).max() <= reach


@pytest.mark.parametrize("name", ROBOTS)
def test_select_equals_fk_of_the_subset(name):
    r = get_robot(name)
    q = r.random_q(300, torch.Generator().manual_seed(3))
    idx = torch.arange(5, 300, 7)
    sub, ref = r.chain.select(r.kinematics(q, ee=False), idx), r.kinematics(q[idx])
    for f in ("axes", "origins", "points", "ee_pos", "ee_rot"):
        torch.testing.assert_close(getattr(sub, f), getattr(ref, f), rtol=0, atol=1e-14)
    no_points = r.chain.select(r.kinematics(q, ee=False), idx, points=False)
    assert no_points.points is None
    torch.testing.assert_close(no_points.ee_pos, ref.ee_pos, rtol=0, atol=1e-14)


def gantry(revolute_middle: bool = False):
    """A translational chain that is not the identity: three prismatic joints with rotated origins and skew axes,
    points on three links (one on the root), the end effector behind a fixed rotated joint; with ``revolute_middle``
    its second joint is revolute (a chain of both kinds, on the general pass)."""
    from mpd.robots.chain import ChainFrame, KinematicChain, rpy_to_matrix

    def T(rpy, xyz):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rpy_to_matrix(rpy), xyz
        return m

    frames = [
        ChainFrame("base", None, "fixed", np.eye(4), np.zeros(3)),
        ChainFrame("l1", "j1", "prismatic", T((0.3, -0.2, 0.9), (0.1, 0.2, 0.3)), np.array([1.0, 0.5, 0.0])),
        ChainFrame(
            "l2",
            "j2",
            "revolute" if revolute_middle else "prismatic",
            T((-0.7, 0.1, 0.4), (0.0, -0.4, 0.2)),
            np.array([0.0, 1.0, 2.0]),
        ),
        ChainFrame("l2b", "f", "fixed", T((0.5, 0.5, -0.5), (0.05, 0.0, 0.1)), np.zeros(3)),
        ChainFrame("l3", "j3", "prismatic", T((0.2, 0.3, -1.1), (0.3, 0.1, -0.2)), np.array([0.2, -1.0, 0.7])),
        ChainFrame("tool", "g", "fixed", T((1.0, 0.0, 0.3), (0.0, 0.0, 0.15)), np.zeros(3)),
    ]
    links = ["base", "l1", "l1", "l2b", "l3", "tool"]
    offsets = np.array([[0.1, 0, 0], [0.0, 0.1, 0.2], [0.3, -0.1, 0], [0, 0, 0.1], [0.2, 0.2, 0.2], [0, 0.05, 0]])
    return KinematicChain(frames, links, offsets, "tool")


def test_translational_chain_fk_and_jacobian_products_match_the_general_pass():
    """The affine FK of a chain without revolute joints against the general pass (which it replaces for such chains)
    and the batch-first formulation; its three Jacobian products against autograd through the general pass."""
    chain = gantry()
    assert chain.translational and not get_robot("RobotPanda").chain.translational
    q = torch.randn(500, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    kin = chain.forward(q)
    assert kin.frames_t is None
    gen = chain._forward_general(q, points=True, ee=True, exact=False)
    ref = batch_first_fk(chain, q)
    for f, want in zip(("axes", "origins", "points", "ee_pos", "ee_rot"), ref):
        torch.testing.assert_close(getattr(kin, f), getattr(gen, f), rtol=0, atol=1e-14)
        torch.testing.assert_close(getattr(kin, f), want, rtol=0, atol=1e-14)
    for points, ee in ((False, True), (True, False), (False, False)):
        k = chain.forward(q, points=points, ee=ee)
        assert (k.points is None) != points and (k.ee_pos is None) != ee
        torch.testing.assert_close(k.origins, gen.origins, rtol=0, atol=1e-14)
        if ee:
            torch.testing.assert_close(k.ee_pos, gen.ee_pos, rtol=0, atol=1e-14)
    sub = chain.select(kin, torch.arange(3, 500, 11))
    torch.testing.assert_close(sub.ee_pos, gen.ee_pos[3::11], rtol=0, atol=1e-14)
    # J^T g of the points: autograd through the general pass
    g = torch.randn(6, 3, 500, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    qa = q.clone().requires_grad_(True)
    (auto,) = torch.autograd.grad((chain._forward_general(qa, True, False, False).points_t * g).sum(), qa)
    torch.testing.assert_close(chain.points_vjp(kin, g.permute(2, 0, 1)), auto, rtol=0, atol=1e-12)
    torch.testing.assert_close(chain.points_vjp_frames(kin, g), auto, rtol=0, atol=1e-12)
    # from the moments the collision kernel accumulates: H[f - 1, m, k] = sum over the points on frame f
    frame, lw = chain.point_moments_weights(torch.float64)
    H = torch.zeros(3, 4, 3, 500, dtype=torch.float64)
    for s, f in enumerate(frame):
        if f > 0:
            H[f - 1] += torch.as_tensor(lw[s])[:, None, None] * g[s][None]
    torch.testing.assert_close(chain.vjp_from_moments(kin, H), auto, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", [*ROBOTS, "mixed"])
def test_compiled_fk_pass_is_the_torch_pass(name, dtype):
    """The compiled FK (``mpd.robots.fk_kernel``) against the torch pass it replaces on the CPU: frames, axes, origins,
    points and the end-effector pose; the same products term by term, so equal to the last bits that a BLAS kernel's
    own order of a 3- or 4-term sum can change. Batches that are not a multiple of the kernel's block included."""
    from mpd import kernels

    chain = gantry(revolute_middle=True) if name == "mixed" else get_robot(name).chain
    q = torch.randn(1500, chain.dof, generator=torch.Generator().manual_seed(8), dtype=dtype) * 1.5
    got = chain.forward(q)
    with kernels.use("torch", "fk"):
        want = chain.forward(q)
    if chain.translational:
        assert got.frames_t is None and want.frames_t is None
    tol = {"rtol": 0, "atol": 2e-6 if dtype == torch.float32 else 1e-14}
    for f in ("frames_t", "axes_t", "origins_t", "points_t", "ee_pos", "ee_rot"):
        if getattr(want, f) is not None:
            torch.testing.assert_close(getattr(got, f), getattr(want, f), **tol)
    for n in (0, 1, 513):  # an empty batch, one configuration, one past a block
        k = chain.forward(q[:n], ee=False)
        with kernels.use("torch", "fk"):
            torch.testing.assert_close(k.points_t, chain.forward(q[:n], ee=False).points_t, **tol)
