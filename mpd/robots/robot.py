"""Robots: joint limits, batched FK of collision spheres and end effector, Jacobian products, self-collision pairs."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch

from mpd.robots.chain import ChainFrame, KinematicChain, Kinematics, rpy_to_matrix
from mpd.robots.spec import RobotSpec, load_robot_spec


def _quiet_pk():
    import pytorch_kinematics as pk
    from pytorch_kinematics.urdf_parser_py.xml_reflection import core

    core.on_error = lambda msg: None  # pybullet_data's URDF has tags pk does not know; harmless
    return pk


@functools.lru_cache(maxsize=8)
def pk_serial_chain(urdf_path: str, end_link: str):
    """pytorch-kinematics chain of a URDF (float64, CPU): the reference FK/Jacobian for tests."""
    pk = _quiet_pk()
    return pk.build_serial_chain_from_urdf(Path(urdf_path).read_bytes(), end_link_name=end_link).to(dtype=torch.float64)


def _frames_from_joints(spec: RobotSpec) -> list[ChainFrame]:
    frames = [ChainFrame(spec.joints[0].parent, None, "fixed", np.eye(4), np.zeros(3))]
    prev = spec.joints[0].parent
    for j in spec.joints:
        if j.parent != prev:
            raise ValueError(f"joint {j.name!r}: parent {j.parent!r} does not follow {prev!r} (chains must be serial)")
        T = np.eye(4)
        T[:3, :3] = rpy_to_matrix(j.rpy)
        T[:3, 3] = j.xyz
        frames.append(ChainFrame(j.child, j.name, j.type, T, np.asarray(j.axis, dtype=np.float64)))
        prev = j.child
    return frames


def _frames_from_urdf(spec: RobotSpec) -> list[ChainFrame]:
    chain = pk_serial_chain(str(spec.urdf.resolve()), spec.urdf.end_link)
    frames = []
    f = chain._root
    while True:
        off = f.joint.offset.get_matrix()[0].numpy() if f.joint.offset is not None else np.eye(4)
        link_off = f.link.offset.get_matrix()[0].numpy() if f.link.offset is not None else np.eye(4)
        if not np.allclose(link_off, np.eye(4)):
            raise ValueError(f"link {f.link.name!r} has a non-identity link offset; not supported")
        jt = f.joint.joint_type if f.joint.joint_type in ("revolute", "prismatic") else "fixed"
        frames.append(ChainFrame(f.link.name, f.joint.name, jt, off, f.joint.axis.numpy().astype(np.float64)))
        if not f.children:
            break
        f = f.children[0]
    return frames


class Robot:
    """A robot of the benchmark. All batched methods take q of shape (..., dof) on any device and dtype."""

    def __init__(self, spec: RobotSpec):
        self.spec = spec
        self.name = spec.name
        self.task_dim = spec.task_dim
        frames = _frames_from_urdf(spec) if spec.urdf is not None else _frames_from_joints(spec)
        self.sphere_links = [s.link for s in spec.spheres]
        self.chain = KinematicChain(frames, self.sphere_links, np.array([s.centre for s in spec.spheres]), spec.ee_link)
        self.dof = self.chain.dof
        self.joint_names = self.chain.joint_names
        lim = spec.limits
        self.q_min = torch.tensor([lo for lo, _ in lim.position], dtype=torch.float64)
        self.q_max = torch.tensor([hi for _, hi in lim.position], dtype=torch.float64)
        self.dq_max = torch.tensor(lim.velocity, dtype=torch.float64) if lim.velocity else None
        self.ddq_max = torch.tensor(lim.acceleration, dtype=torch.float64) if lim.acceleration else None
        self.sphere_radii = torch.tensor([s.radius for s in spec.spheres], dtype=torch.float64)
        self.n_spheres = len(spec.spheres)
        pairs = []
        for a, b in spec.self_collision.link_pairs:
            ia = [i for i, n in enumerate(self.sphere_links) if n == a]
            ib = [i for i, n in enumerate(self.sphere_links) if n == b]
            if not ia or not ib:
                raise ValueError(f"self_collision pair ({a!r}, {b!r}) names a link without spheres")
            pairs += [(i, j) for i in ia for j in ib]
        self.self_pairs = torch.tensor(pairs, dtype=torch.long).reshape(-1, 2)

    def __repr__(self) -> str:
        return f"Robot({self.name}, dof={self.dof}, spheres={self.n_spheres}, self_pairs={len(self.self_pairs)})"

    # ------------------------------------------------------------------ limits and sampling
    def limits(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.q_min.to(like), self.q_max.to(like)

    def random_q(self, n: int, generator: torch.Generator | None = None, dtype=torch.float64) -> torch.Tensor:
        """Uniform configurations within the position limits."""
        u = torch.rand(n, self.dof, generator=generator, dtype=dtype)
        return self.q_min.to(dtype) + u * (self.q_max - self.q_min).to(dtype)

    def within_limits(self, q: torch.Tensor, eps: float = 0.0) -> torch.Tensor:
        lo, hi = self.limits(q)
        return ((q >= lo - eps) & (q <= hi + eps)).all(-1)

    # ------------------------------------------------------------------ kinematics
    def kinematics(self, q: torch.Tensor, *, spheres: bool = True, ee: bool = True, exact: bool = False) -> Kinematics:
        """FK for q of shape (B, dof); the batch must be flat. ``exact``: see :meth:`ee_pose`."""
        return self.chain.forward(q, points=spheres, ee=ee, exact=exact)

    def sphere_centres(self, q: torch.Tensor) -> torch.Tensor:
        """(..., dof) -> (..., S, task_dim)."""
        shape = q.shape[:-1]
        kin = self.chain.forward(q.reshape(-1, self.dof), points=True, ee=False)
        # contiguous: kin.points may be a batch-last view, on which the norms and gathers of the validity
        # checks (self-collision pairs, grid lookups) run 10-15x slower than the copy costs
        return kin.points[..., : self.task_dim].reshape(*shape, self.n_spheres, self.task_dim).contiguous()

    def ee_pose(self, q: torch.Tensor, exact: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., dof) -> position (..., 3), rotation (..., 3, 3) of the end effector (3-D, also for planar arms).
        ``exact``: the same bits on every CPU (:mod:`mpd.robots.exact`; the data-generation path)."""
        shape = q.shape[:-1]
        kin = self.chain.forward(q.reshape(-1, self.dof), points=False, ee=True, exact=exact)
        return kin.ee_pos.reshape(*shape, 3), kin.ee_rot.reshape(*shape, 3, 3)

    def ee_jacobian(self, q: torch.Tensor) -> torch.Tensor:
        """Geometric Jacobian (..., 6, dof) of the end effector, world frame, rows [v; w]."""
        shape = q.shape[:-1]
        kin = self.chain.forward(q.reshape(-1, self.dof), points=False, ee=True)
        return self.chain.ee_jacobian(kin).reshape(*shape, 6, self.dof)

    def spheres_vjp(self, kin: Kinematics, g: torch.Tensor) -> torch.Tensor:
        """Map dC/d(sphere centres) (B, S, task_dim) to dC/dq (B, dof)."""
        if g.shape[-1] == 2:
            g = torch.nn.functional.pad(g, (0, 1))
        return self.chain.points_vjp(kin, g)

    def ee_vjp(self, kin: Kinematics, g_pos: torch.Tensor, g_rot: torch.Tensor) -> torch.Tensor:
        """Map a task-space gradient (dC/dp (B,3), dC/dw (B,3) with w the world-frame rotation increment) to dC/dq."""
        J = self.chain.ee_jacobian(kin)
        return torch.einsum("bi,bij->bj", g_pos, J[:, :3]) + torch.einsum("bi,bij->bj", g_rot, J[:, 3:])

    # ------------------------------------------------------------------ self collision
    def self_collision_distance(self, centres: torch.Tensor) -> torch.Tensor:
        """Signed clearance of every self-collision pair: ||c_i - c_j|| - r_i - r_j, shape (..., P)."""
        if len(self.self_pairs) == 0:
            return centres.new_zeros(*centres.shape[:-2], 0)
        i, j = self.self_pairs[:, 0].to(centres.device), self.self_pairs[:, 1].to(centres.device)
        r = self.sphere_radii.to(centres)
        # index_select: 2-3x faster than advanced indexing of a middle dimension on CPU
        d = (centres.index_select(-2, i) - centres.index_select(-2, j)).norm(dim=-1)
        return d - r[i] - r[j]


@functools.lru_cache(maxsize=16)
def get_robot(name_or_path: str) -> Robot:
    """Robots are immutable; one instance per description file."""
    return Robot(load_robot_spec(name_or_path))
