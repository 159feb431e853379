"""The kinematic-chain additions made for the costs: the batch-last FK against the batch-first formulation it
replaced, the frame-based Jacobian product, the reach bound, and the sparse product of ``mpd.costs``."""

from __future__ import annotations

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
    assert kin.points.data_ptr() == kin.points_t.data_ptr() and kin.frames_t.shape == (r.dof + 1, 4, 3, 3000)


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
