"""GPprior+Cost: the paper's uninformed baseline (essentially CHOMP).

Trajectories are drawn from a Gaussian-process prior around the straight line from start to goal in joint space,
then optimized with the same gradient routine and step count as every "+Cost" baseline. The GP acts on the free
control points: the mean puts them on the straight line (at their Greville phases, so the curve is the segment),
the covariance is a squared-exponential kernel over phase, conditioned to vanish at both ends (a bridge), in
unit-normalized space. With an end-effector goal the goal configuration comes from batched inverse kinematics,
one solution per sample from random restarts (different samples may reach different goal configurations).
"""

from __future__ import annotations

import numpy as np
import torch

from mpd.planners.base import Context, HistoryStep, Planner, Timer, register
from mpd.planners.optimize import optimize


def bridge_covariance(phases: np.ndarray, lengthscale: float) -> np.ndarray:
    """Squared-exponential covariance over ``phases`` conditioned on zero deviation at phase 0 and 1."""
    s = np.asarray(phases, dtype=np.float64)
    k = lambda a, b: np.exp(-((a[:, None] - b[None, :]) ** 2) / (2 * lengthscale**2))  # noqa: E731
    ends = np.array([0.0, 1.0])
    kxx, kxe, kee = k(s, s), k(s, ends), k(ends, ends)
    cov = kxx - kxe @ np.linalg.solve(kee, kxe.T)
    return (cov + cov.T) / 2


@register
class GPPriorCost(Planner):
    name = "gp-cost"
    label = "GPprior+Cost"
    unused_axes = ("sampler",)
    parametrizations = ("bspline",)  # "all baselines use the B-spline parametrization"

    def _goal_configurations(self, ctx: Context, n: int, gen: torch.Generator, timer: Timer) -> torch.Tensor:
        if ctx.q_goal is not None:
            return ctx.q_goal.expand(n, -1)
        from mpd.planners.goals import ik_goals

        with timer("ik"):
            return ik_goals(self.task, self.env, ctx, n, gen, restarts=self.settings.ik_restarts).to(
                ctx.q_start
            )

    def sample_prior(self, ctx: Context, n: int, gen: torch.Generator, timer: Timer) -> torch.Tensor:
        """n samples of the free rows (normalized), around the straight line from q_start to the goal."""
        q_goal = self._goal_configurations(ctx, n, gen, timer)
        ph = self.param.param_phases()
        rows = self.param.a_free.argmax(0)  # the parameter row of each free row
        ph_free = ph[rows]
        qs = self.normalizer.normalize(ctx.q_start)[None, None, :]
        qg = self.normalizer.normalize(q_goal)[:, None, :]
        t = torch.as_tensor(ph_free, dtype=qs.dtype, device=qs.device)[None, :, None]
        mean = qs + t * (qg - qs)  # (n, n_free, dof)
        cov = bridge_covariance(ph_free, self.settings.gp_lengthscale)
        L = torch.as_tensor(
            np.linalg.cholesky(cov + 1e-9 * np.eye(len(ph_free))), dtype=qs.dtype, device=qs.device
        )
        z = torch.randn(n, len(ph_free), self.task.dof, generator=gen, device=gen.device).to(qs)
        x = mean + self.settings.gp_sigma * (L @ z)
        if self.param.ee_goal:  # the final configuration is the IK goal itself (zero deviation at phase 1)
            x[:, -1] = qg[:, 0]
        return x

    def plan(self, ctx: Context, n_samples: int, seed: int, record_history: bool = False):
        gen = torch.Generator(device=self.device).manual_seed(seed)
        timer = Timer(self.device)
        hist: list[HistoryStep] | None = [] if record_history else None
        s = self.settings
        with timer("total"):
            x0 = self.sample_prior(ctx, n_samples, gen, timer)
            if hist is not None:
                hist.append(HistoryStep("prior", 0, self.normalizer.unnormalize(x0)))
            cb = (
                None
                if hist is None
                else (
                    lambda k, x: hist.append(
                        HistoryStep("optimization", k + 1, self.normalizer.unnormalize(x))
                    )
                )
            )
            x = optimize(
                x0,
                self.cost_grad_fn(ctx, timer),
                s.opt_steps,
                s.opt_lr,
                s.opt_max_perturb,
                s.opt_grad_clip,
                cb,
            )
            free = self.normalizer.unnormalize(x)
        return self.finish(free, ctx, timer, hist)
