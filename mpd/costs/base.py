"""What every cost shares: the per-evaluation input, a cost's result, the base class and the registry.

A cost sees one :class:`CostInput` per evaluation: the dense trajectories (B, n, dof) and, computed lazily and
only once for all costs, the forward kinematics of all B*n configurations in the chain's batch-last layout
(sphere centres (S, 3, B*n)). It returns a :class:`CostTerm`: its value per trajectory and the gradient of
``weight * value`` w.r.t. the dense q, q', q''. Folding the weight into the per-point factors costs nothing,
while scaling a task-space gradient afterwards would be one more pass over (S, 3, B*n) numbers. The composite
(:mod:`mpd.costs.composite`) maps the sum of all those gradients to the free control points with one product.

Phase integrals (section "Motion Planning Costs" of the paper): C = lambda * int_0^1 C(s) (dt/ds) ds with
dt/ds = T, on the n equidistant phase points. The ``official`` preset (the authors' configs) uses the
trapezoid rule, the ``paper`` preset a plain Riemann sum (Delta s * T per point); see :func:`phase_weights`.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import ClassVar

import torch

from mpd.envs import Environment
from mpd.robots import Robot
from mpd.robots.chain import Kinematics
from mpd.tasks import Task
from mpd.trajectory import Dense

PRESETS = ("official", "paper")
SDF_MODES = ("nearest", "trilinear", "analytic", "authors")

COSTS: dict[str, type[Cost]] = {}


def register(cls: type[Cost]) -> type[Cost]:
    """Class decorator: make a cost available under its ``name`` (a field of the task's cost weights)."""
    if cls.name in COSTS:
        raise ValueError(f"cost {cls.name!r} registered twice")
    COSTS[cls.name] = cls
    return cls


def phase_weights(n: int, duration: float, rule: str, dtype: torch.dtype, device) -> torch.Tensor:
    """Quadrature weights (n,) of int_0^1 f(s) T ds on n equidistant phases: ``trapezoid`` or ``riemann``."""
    w = torch.full((n,), duration / (n - 1), dtype=dtype, device=device)
    if rule == "trapezoid":
        w[0] = w[-1] = duration / (n - 1) / 2
    elif rule != "riemann":
        raise ValueError(f"unknown integration rule {rule!r} (trapezoid, riemann)")
    return w


@dataclass
class CostInput:
    """Everything computed once per evaluation and shared by all costs.

    Args:
        dense: the trajectories, each field (B, n, dof).
        task: the task (robot, margins).
        env: the environment the collision costs see (training scene or with extra objects).
        ee_goal: (position (B, 3), rotation (B, 3, 3)) of the end-effector goal, or None.
        sdf_mode: ``nearest`` (the paper's grid lookup), ``trilinear``, ``analytic`` or ``authors`` (their
            off-by-one lookup: a measurement).
    """

    dense: Dense
    task: Task
    env: Environment
    ee_goal: tuple[torch.Tensor, torch.Tensor] | None = None
    sdf_mode: str = "nearest"
    _kin: Kinematics | None = field(default=None, init=False, repr=False)
    _last_kin: Kinematics | None = field(default=None, init=False, repr=False)

    @property
    def robot(self) -> Robot:
        return self.task.robot

    @property
    def shape(self) -> tuple[int, int, int]:
        """(B, n, dof)."""
        return tuple(self.dense.q.shape)

    def kinematics(self) -> Kinematics:
        """FK of all B*n configurations (row b*n + i is point i of trajectory b), sphere centres only."""
        if self._kin is None:
            B, n, dof = self.shape
            self._kin = self.robot.kinematics(self.dense.q.reshape(B * n, dof), spheres=True, ee=False)
        return self._kin

    def last_kinematics(self) -> Kinematics:
        """Kinematics of the final configuration q(1) of every trajectory, with the end-effector pose and without the
        attached points: taken from :meth:`kinematics` when that has run (the collision costs run first), else one
        FK of B configurations."""
        if self._last_kin is None:
            B, n, _ = self.shape
            if self._kin is not None:
                idx = torch.arange(n - 1, B * n, n, device=self.dense.q.device)
                self._last_kin = self.robot.chain.select(self._kin, idx, points=False)
            else:
                self._last_kin = self.robot.kinematics(self.dense.q[:, -1].contiguous(), spheres=False, ee=True)
        return self._last_kin

    def final_columns(self) -> tuple[Kinematics, torch.Tensor]:
        """A kinematics that holds the final configurations q(1) and their columns (B,) in it: the FK of all
        configurations when that has run (columns n - 1, 2n - 1, ...), else :meth:`last_kinematics` (0 .. B - 1)."""
        B, n, _ = self.shape
        dev = self.dense.q.device
        if self._kin is not None:
            return self._kin, torch.arange(n - 1, B * n, n, device=dev)
        return self.last_kinematics(), torch.arange(B, device=dev)


@dataclass
class CostTerm:
    """One cost's contribution. ``value`` (B,) is the unweighted cost; the gradients, each (B, n, dof) or
    None, are those of ``weight * value`` w.r.t. the dense q, q' (= dq/ds) and q'' (= d2q/ds2)."""

    value: torch.Tensor
    g_q: torch.Tensor | None = None
    g_dq: torch.Tensor | None = None
    g_ddq: torch.Tensor | None = None


class Cost:
    """Base class of the motion-planning costs: one subclass per file, registered with :func:`register`.

    Args:
        task: the task (robot, margins, duration).
        preset: ``official`` (the authors' configs) or ``paper`` (the paper's formulas); see each cost.
    """

    name: ClassVar[str] = ""

    def __init__(self, task: Task, preset: str = "official"):
        if preset not in PRESETS:
            raise ValueError(f"unknown cost preset {preset!r} ({', '.join(PRESETS)})")
        self.task = task
        self.robot = task.robot
        self.preset = preset
        self._consts: dict[tuple, dict[str, torch.Tensor]] = {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}(preset={self.preset!r})"

    @classmethod
    def applicable(cls, task: Task) -> bool:
        """False when the cost has nothing to act on in this task (it is then skipped entirely)."""
        return True

    def weights(self, inp: CostInput) -> torch.Tensor:
        """Per-point quadrature weights (n,) of the phase integral for this preset."""
        q = inp.dense.q
        key = ("phase", q.shape[1], inp.dense.duration, q.dtype, str(q.device))
        if key not in self._consts:
            rule = "trapezoid" if self.preset == "official" else "riemann"
            self._consts[key] = {"w": phase_weights(q.shape[1], inp.dense.duration, rule, q.dtype, q.device)}
        return self._consts[key]["w"]

    def __call__(self, inp: CostInput, weight: float = 1.0) -> CostTerm:
        raise NotImplementedError

    # Costs that are a per-point penalty on the dense fields also say so (a ``mpd.costs.phase_kernel.Penalty``), so
    # that the cost function can run them together in one compiled pass; ``__call__`` stays their reference.
    penalty = None


def spheres_vjp_sparse(
    robot: Robot, kin: Kinematics, flat: torch.Tensor, g: torch.Tensor, n_configs: int
) -> torch.Tensor:
    """dC/dq (N, dof) from a sphere-centre gradient given only where it is non-zero.

    ``flat`` (E,) indexes the entries of the batch-last (S, N) grid, s * N + configuration (as from
    ``mask.view(-1).nonzero()``), and ``g`` (E, D) is the gradient w.r.t. those sphere centres. The product is
    the one of ``Robot.spheres_vjp`` (see :mod:`mpd.robots.chain`), (J^T g)_j = z_j . (M_j - o_j x F_j) with
    F_j, M_j the sums of g_s and c_s x g_s over the spheres below joint j, accumulated from the E entries: one
    ``index_add`` per (frame, configuration), then sums over the frames below each joint, and the joint-axis
    products only for the configurations that have an entry. The collision costs touch a small part of the S x
    N grid (17 % of it for 100 random straight Panda trajectories in EnvSpheres3D, fewer after guidance, a few
    entries for self collision), and this costs O(E + touched configurations) instead of O(S N).
    """
    chain = robot.chain
    dof, N = chain.dof, n_configs
    key = (g.dtype, str(g.device))
    c = _SPARSE_CACHE.setdefault(chain, {})
    if key not in c:
        c[key] = (
            torch.as_tensor(chain.point_joint, device=g.device),
            torch.as_tensor(chain.revolute, device=g.device)[:, None, None],
        )
    frame_of, revolute = c[key]
    out = g.new_zeros(N, dof)
    if flat.numel() == 0:
        return out
    sphere = flat // N
    config = flat - sphere * N
    frame = frame_of.index_select(0, sphere)
    if bool((frame < 0).any()):  # spheres on the root link move with no joint
        keep = frame >= 0
        flat, g, sphere, config, frame = flat[keep], g[keep], sphere[keep], config[keep], frame[keep]
    # the configurations that have entries, numbered 0..U-1
    touched = torch.zeros(N, dtype=torch.bool, device=g.device)
    touched[config] = True
    cfg = touched.nonzero().squeeze(1)
    U = cfg.numel()
    local = torch.empty(N, dtype=torch.long, device=g.device)
    local[cfg] = torch.arange(U, device=g.device)
    # rows [g, c x g] of every entry; the centre c is read from the flat (S, 3, N) buffer at s*3N + k*N + n
    E = flat.numel()
    rows = g.new_zeros(E, 6)
    rows[:, : g.shape[1]] = g
    base = flat + sphere * (2 * N)
    Xf = kin.points_t.reshape(-1)
    x = [Xf.index_select(0, base + k * N) for k in range(3)]
    gc = [rows[:, k] for k in range(3)]
    for k, (k1, k2) in enumerate(((1, 2), (2, 0), (0, 1))):
        rows[:, 3 + k] = x[k1] * gc[k2] - x[k2] * gc[k1]
    acc = g.new_zeros(dof * U, 6)
    acc.index_add_(0, frame * U + local.index_select(0, config), rows)
    acc = acc.view(dof, U, 6)
    for j in range(dof - 2, -1, -1):  # joint j collects the frames j..dof-1
        acc[j] += acc[j + 1]
    F, M = acc[..., :3].permute(0, 2, 1), acc[..., 3:].permute(0, 2, 1)  # (dof, 3, U)
    o, z = kin.origins_t.index_select(2, cfg), kin.axes_t.index_select(2, cfg)
    t = torch.stack([o[:, k1] * F[:, k2] - o[:, k2] * F[:, k1] for k1, k2 in ((1, 2), (2, 0), (0, 1))], 1)
    t = (M - t if chain.revolute.all() else torch.where(revolute, M - t, F)) * z
    out.index_copy_(0, cfg, (t[:, 0] + t[:, 1] + t[:, 2]).t())
    return out


_SPARSE_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # chain -> {(dtype, device): consts}


def parity_case(task_name: str, dtype: torch.dtype, batch: int, seed: int, extra_objects: bool = True) -> tuple:
    """(task, parametrization, env, free, q_start, q_goal, ee_goal): ``batch`` B-spline trajectories through random
    configurations of the task's robot (seeded) and their goals (end-effector goals at the poses of random
    configurations, q_goal None, for a task of such goals, else joint goals and ee_goal None): the inputs of the
    cost kernels' parity cases (:mod:`mpd.kernels`)."""
    from mpd.tasks import load_task
    from mpd.trajectory import make_parametrization

    task = load_task(task_name)
    param = make_parametrization(task, "bspline")
    r, g = task.robot, torch.Generator().manual_seed(seed)
    free = r.random_q(batch * param.n_free, g).view(batch, param.n_free, r.dof).to(dtype)
    q_start, q_goal = r.random_q(batch, g).to(dtype), r.random_q(batch, g).to(dtype)
    ee_goal = tuple(x.to(dtype) for x in r.ee_pose(r.random_q(batch, g)))
    q_goal, ee_goal = (None, ee_goal) if task.ee_goal else (q_goal, None)
    return task, param, task.env(extra_objects=extra_objects), free, q_start, q_goal, ee_goal


def cost_parity(name: str, dtype: torch.dtype, seed: int):
    """The ``run()`` of a cost kernel's parity case (:mod:`mpd.kernels`): the value and joint gradient of cost
    ``name`` (weight 2) on 24 Panda trajectories through random configurations of EnvSpheres3D with its extra objects
    (a fresh cost input each run)."""
    task, param, env, free, q_start, q_goal, ee_goal = parity_case("EnvSpheres3D-RobotPanda", dtype, 24, seed)
    cost = COSTS[name](task, "official")

    def run() -> dict:
        inp = CostInput(param.dense(free, q_start, q_goal), task, env, ee_goal, "nearest")
        term = cost(inp, 2.0)
        return {"value": term.value, "g_q": term.g_q}

    return run
