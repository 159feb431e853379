"""Batched validity of configurations and dense trajectories: environment collision, self collision, joint limits.

This is the ground-truth checker used for datasets, evaluation contexts and metrics. A robot sphere collides with the
scene iff ``sdf(centre) <= radius + margin``; a self-collision pair collides iff ``||c_i - c_j|| < r_i + r_j``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mpd.tasks import Task


@dataclass
class Validity:
    """Per configuration (or per trajectory, for :meth:`CollisionChecker.trajectories`) flags; True = fine."""

    env_free: torch.Tensor
    self_free: torch.Tensor
    pos_ok: torch.Tensor
    vel_ok: torch.Tensor
    acc_ok: torch.Tensor

    @property
    def collision_free(self) -> torch.Tensor:
        return self.env_free & self.self_free

    @property
    def limits_ok(self) -> torch.Tensor:
        return self.pos_ok & self.vel_ok & self.acc_ok

    @property
    def valid(self) -> torch.Tensor:
        return self.collision_free & self.limits_ok


class CollisionChecker:
    """Validity checks of one task environment (training scene or with extra objects, possibly rotated).

    Args:
        sdf_mode: ``analytic`` (exact, the default for evaluation) or ``nearest``/``trilinear`` (the grid SDF).
        margin: extra clearance required from obstacles (default: the task's ``collision.validity_margin``).
        env: the scene itself (e.g. one with obstacles given at plan time); replaces ``extra_objects`` and
            ``rotation_deg``.
    """

    def __init__(
        self,
        task: Task,
        extra_objects: bool = False,
        rotation_deg: float = 0.0,
        sdf_mode: str = "analytic",
        margin: float | None = None,
        env=None,
    ):
        self.task = task
        self.robot = task.robot
        self.env = task.env(extra_objects, rotation_deg) if env is None else env
        self.sdf_mode = sdf_mode
        self.margin = task.spec.collision.validity_margin if margin is None else float(margin)
        self.self_collision = task.spec.collision.self_collision

    def env_clearance(self, q: torch.Tensor, chunk: int = 1 << 14) -> torch.Tensor:
        """Smallest sdf(centre) - radius over the robot spheres, shape (...)."""
        shape = q.shape[:-1]
        flat = q.reshape(-1, self.robot.dof)
        out = []
        r = self.robot.sphere_radii.to(q)
        for s in range(0, flat.shape[0], chunk):
            c = self.robot.sphere_centres(flat[s : s + chunk])
            d = self.env.sdf(c, mode=self.sdf_mode)
            out.append((d - r).min(-1).values)
        return torch.cat(out).reshape(shape)

    def self_clearance(self, q: torch.Tensor, chunk: int = 1 << 14) -> torch.Tensor:
        """Smallest ||c_i - c_j|| - r_i - r_j over the self-collision pairs (+inf without pairs), shape (...)."""
        if not self.self_collision or len(self.robot.self_pairs) == 0:
            return torch.full(q.shape[:-1], float("inf"), dtype=q.dtype, device=q.device)
        # chunked like env_clearance: 100k Panda configurations x 280 pairs would otherwise hold ~2 GB of pair
        # differences at once
        flat = q.reshape(-1, self.robot.dof)
        out = []
        for s in range(0, flat.shape[0], chunk):
            d = self.robot.self_collision_distance(self.robot.sphere_centres(flat[s : s + chunk]))
            out.append(d.min(-1).values)
        return torch.cat(out).reshape(q.shape[:-1])

    def configs(self, q: torch.Tensor, margin: float | None = None) -> Validity:
        """Validity of configurations q (..., dof)."""
        m = self.margin if margin is None else margin
        env_free = self.env_clearance(q) > m
        self_free = self.self_clearance(q) >= 0
        pos_ok = self.robot.within_limits(q)
        ones = torch.ones_like(pos_ok)
        return Validity(env_free, self_free, pos_ok, ones, ones)

    def trajectories(
        self, q: torch.Tensor, dq: torch.Tensor | None = None, ddq: torch.Tensor | None = None
    ) -> Validity:
        """Validity of dense trajectories: q, time derivatives dq, ddq of shape (B, n_points, dof).

        A trajectory is valid when every point is collision free and within the position, velocity and acceleration
        limits (the latter two only where the robot defines them).
        """
        c = self.configs(q)
        env_free = c.env_free.all(-1)
        self_free = c.self_free.all(-1)
        pos_ok = c.pos_ok.all(-1)
        vel_ok = torch.ones_like(pos_ok)
        acc_ok = torch.ones_like(pos_ok)
        if dq is not None and self.robot.dq_max is not None:
            vel_ok = (dq.abs() <= self.robot.dq_max.to(dq)).all(-1).all(-1)
        if ddq is not None and self.robot.ddq_max is not None:
            acc_ok = (ddq.abs() <= self.robot.ddq_max.to(ddq)).all(-1).all(-1)
        return Validity(env_free, self_free, pos_ok, vel_ok, acc_ok)


def collision_fractions(task: Task, n: int = 100_000, seed: int = 0) -> dict[str, float]:
    """Share of random samples in collision, per scene: the numbers of the reference's free-space table.

    Point-mass tasks sample workspace points (``inside`` = sdf < 0, ``dilated`` = sdf <= robot radius); arms sample
    configurations uniformly within the joint limits (``env``, ``self``, ``either`` collision).
    """
    g = torch.Generator().manual_seed(seed)
    out: dict[str, float] = {}
    for extra in (False, True):
        tag = "extra" if extra else "train"
        env = task.env(extra)
        if task.robot.dof == task.dim and task.robot.n_spheres == 1:
            lo, hi = (torch.as_tensor(v, dtype=torch.float64) for v in env.workspace)
            x = lo + torch.rand(n, task.dim, generator=g, dtype=torch.float64) * (hi - lo)
            d = env.sdf(x)
            out[f"{tag}/inside"] = (d < 0).double().mean().item()
            out[f"{tag}/dilated"] = (d <= task.robot.sphere_radii[0]).double().mean().item()
        else:
            chk = CollisionChecker(task, extra, margin=0.0)
            q = task.robot.random_q(n, g)
            env_hit = chk.env_clearance(q) <= 0
            self_hit = chk.self_clearance(q) < 0
            out[f"{tag}/env"] = env_hit.double().mean().item()
            out[f"{tag}/self"] = self_hit.double().mean().item()
            out[f"{tag}/either"] = (env_hit | self_hit).double().mean().item()
    return out
