"""The planner's cost: the weighted sum of the task's costs and its gradient w.r.t. the free control points.

One evaluation builds the dense trajectories once, the robot's kinematics once (lazily, shared by the
collision costs), lets every active cost add its gradient w.r.t. the dense q, q', q'', and maps the sum to the
free rows with a single ``grad_to_free`` product. On a CPU the per-point phase costs (velocity, acceleration,
joint limits) run together in one compiled pass (:mod:`mpd.costs.phase_kernel`, timed as ``phase``) that writes
the stacked gradient buffer the other costs add into.

Where the presets differ (each cost's module says more):

| | ``official`` (authors' configs, the default) | ``paper`` |
| --- | --- | --- |
| weights | ``[costs.weights]`` | ``[costs.paper_weights]`` |
| phase integral | trapezoid, dt/ds = T | Riemann sum, Delta s T per point |
| velocity / acceleration | 1/2 sqrt(abs(q')^2 + eta), same for q'' | 1/2 abs(q')^2, 1/2 abs(q'')^2 |
| end-effector pose | 1/2 abs(log_SE3(T_goal T_ee^-1))^2 | 1/2 abs(dp)^2 + 1/2 abs(Log(R_goal^T R_ee))^2 |
| self collision | no margin | + eps |
| EE-goal tasks | EE gradient on the last free row only; the other costs' gradients zeroed there | plain sum |

Joint limits (1/2 abs(violation)^2, margin 0.03) and environment collision (margin ``collision.cost_margin``)
have the same form in both.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields

import numpy as np
import torch

from mpd import kernels
from mpd.costs import phase_kernel
from mpd.costs.base import COSTS, PRESETS, SDF_MODES, Cost, CostInput
from mpd.device import synchronize
from mpd.envs import Environment
from mpd.tasks import Task
from mpd.tasks.spec import CostWeights
from mpd.trajectory import LinearTrajectory


@dataclass
class CostResult:
    """``total`` (B,) = sum of weight * value; ``grad`` (B, n_free, dof) its gradient w.r.t. the free rows;
    ``values`` the unweighted value (B,) of each active cost; ``timings`` seconds per cost (and ``dense``, ``fk``,
    ``chain_rule``; ``phase`` for the costs of the fused pass, which then have no entry of their own) when
    profiling, else None."""

    total: torch.Tensor
    grad: torch.Tensor
    values: dict[str, torch.Tensor]
    weights: dict[str, float]
    timings: dict[str, float] | None = None


class CostFunction:
    """The weighted sum of a task's motion-planning costs.

    Args:
        task: the task (robot, cost margins, weights).
        parametrization: the trajectory parametrization whose free rows the gradient is for.
        env: the environment the collision cost sees.
        preset: ``official`` or ``paper`` (see the module docstring).
        weights: overrides of the preset's weights: a :class:`CostWeights` or a dict ``{name: weight}``.
        sdf_mode: ``nearest`` (the paper), ``trilinear``, ``analytic`` or ``authors`` (their off-by-one
            lookup: a measurement).
        profile: record the wall time of every cost (FK included as its own entry) in the result.

    Costs with weight 0 or nothing to act on (the EE cost on a joint-goal task, self collision when
    ``collision.self_collision`` is false) are not built at all.
    """

    def __init__(
        self,
        task: Task,
        parametrization: LinearTrajectory,
        env: Environment,
        preset: str = "official",
        weights: CostWeights | dict[str, float] | None = None,
        sdf_mode: str = "nearest",
        profile: bool = False,
    ):
        if preset not in PRESETS:
            raise ValueError(f"unknown cost preset {preset!r} ({', '.join(PRESETS)})")
        if sdf_mode not in SDF_MODES:
            raise ValueError(f"unknown sdf_mode {sdf_mode!r} ({', '.join(SDF_MODES)})")
        if parametrization.ee_goal != task.ee_goal:
            raise ValueError(f"the parametrization's ee_goal={parametrization.ee_goal} does not match task {task.name}")
        w = {f.name: getattr(task.cost_weights(preset), f.name) for f in fields(CostWeights)}
        if weights is not None:
            over = weights if isinstance(weights, dict) else {f.name: getattr(weights, f.name) for f in fields(weights)}
            unknown = set(over) - set(COSTS)
            if unknown:
                raise ValueError(f"unknown cost names in weights: {sorted(unknown)} (known: {', '.join(COSTS)})")
            w.update({k: float(v) for k, v in over.items()})
        self.task = task
        self.param = parametrization
        self.env = env
        self.preset = preset
        self.sdf_mode = sdf_mode
        self.profile = profile
        self.terms: list[tuple[Cost, float]] = [
            (cls(task, preset), w[name])
            for name, cls in COSTS.items()
            if w.get(name, 0.0) != 0 and cls.applicable(task)
        ]
        # the per-point phase costs (velocity, acceleration, joint limits) in one compiled pass where it applies
        self.fused = [(c, w) for c, w in self.terms if c.penalty is not None and c.name != "ee_pose"]
        # the authors' rule for end-effector goals: the last free row (the final configuration) follows the EE
        # cost only. q(1) depends on that row alone in both parametrizations (they interpolate it), so the EE
        # gradient maps to it with one coefficient and needs no second chain-rule product.
        self.ee_rule = preset == "official" and task.ee_goal
        if self.ee_rule:
            last = (parametrization.basis @ parametrization.a_free)[-1]
            if np.any(last[:-1] != 0):
                raise ValueError(f"{type(parametrization).__name__}: q(1) must depend on the last free row only")
            self._ee_coef = float(last[-1])

    def __repr__(self) -> str:
        terms = ", ".join(f"{c.name}={w:g}" for c, w in self.terms)
        return f"CostFunction({self.task.name}, {self.preset}, sdf={self.sdf_mode}: {terms})"

    @property
    def names(self) -> list[str]:
        return [c.name for c, _ in self.terms]

    def __call__(
        self,
        free: torch.Tensor,
        q_start: torch.Tensor,
        q_goal: torch.Tensor | None = None,
        ee_goal: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> CostResult:
        """Costs and gradient of free rows (B, n_free, dof) given the context (q_start (B, dof), q_goal (B,
        dof) for joint goals, ee_goal (position (B, 3), rotation (B, 3, 3)) for end-effector goals)."""
        if "ee_pose" in self.names and ee_goal is None:
            raise ValueError(f"task {self.task.name} has an end-effector goal: pass ee_goal=(position, rotation)")
        dev = free.device
        timings: dict[str, float] | None = {} if self.profile else None

        def clock() -> float:
            if timings is not None:
                synchronize(dev)
            return time.perf_counter()

        t0 = clock()
        dense = self.param.dense(free, q_start, q_goal)
        inp = CostInput(dense, self.task, self.env, ee_goal, self.sdf_mode)
        if timings is not None:
            timings["dense"] = clock() - t0
            if any(c.name in ("collision", "self_collision") for c, _ in self.terms):
                t0 = clock()
                inp.kinematics()
                timings["fk"] = clock() - t0
        B = free.shape[0]
        total = torch.zeros(B, dtype=free.dtype, device=dev)
        g = [None, None, None]  # d(weighted sum)/d(q, q', q'')
        g_ee_last = None
        values: dict[str, torch.Tensor] = {}
        terms, G = self.terms, None
        if self.fused and kernels.active("phase", dense.stacked):
            # G (B, 3, n, dof) holds the phase costs' gradients; the other costs add theirs into it
            t0 = clock()
            w = self.fused[0][0].weights(inp)
            vals, G = phase_kernel.phase_pass(dense.stacked, w, [(c.penalty(inp), wt) for c, wt in self.fused])
            for (cost, weight), v in zip(self.fused, vals):
                values[cost.name] = v
                total += weight * v
            g = [G[:, 0], G[:, 1], G[:, 2]]
            terms = [t for t in self.terms if t not in self.fused]
            if timings is not None:
                timings["phase"] = clock() - t0
        for cost, weight in terms:
            t0 = clock()
            term = cost(inp, weight)
            values[cost.name] = term.value
            total += weight * term.value
            if self.ee_rule and cost.name == "ee_pose":
                g_ee_last = term.g_q[:, -1]
            else:
                for k, gk in enumerate((term.g_q, term.g_dq, term.g_ddq)):
                    if gk is not None:
                        g[k] = gk if g[k] is None else g[k].add_(gk)
            if timings is not None:
                timings[cost.name] = clock() - t0
        t0 = clock()
        if G is not None:
            grad = self.param.grad_to_free_stacked(G)
        elif all(x is None for x in g):
            grad = torch.zeros_like(free)
        else:
            grad = self.param.grad_to_free(*g)
        if self.ee_rule:
            grad[:, -1] = 0
            if g_ee_last is not None:
                grad[:, -1] = self._ee_coef * g_ee_last
        if timings is not None:
            timings["chain_rule"] = clock() - t0
        return CostResult(total, grad, values, {c.name: w for c, w in self.terms}, timings)
