"""RRTConnect+Cost: the paper's Fig. 10 baseline.

One OMPL RRTConnect path per sample (the paper uses one sample) in the evaluation scene, with the same planner,
validity checker and simplification as the dataset generator, fitted to the task's parametrization, then optimized
with the routine and step count shared by every "+Cost" baseline. With an end-effector goal, the goal configuration
is the one the context carries (``Context.q_goal_ref``, the dataset's, as the authors do); a context without one gets
batched inverse kinematics. A problem RRTConnect does not solve in its time limit falls back to the
straight line (counted in ``info['rrt_failures']``), so the batch always has ``n_samples`` trajectories.
``planner.opt_steps = 0`` gives plain RRTConnect (the sampling-time experiment).
"""

from __future__ import annotations

import numpy as np
import torch

from mpd.planners.base import Context, HistoryStep, Planner, Timer, register
from mpd.planners.prior_cost import optimize_samples


@register
class RRTConnectCost(Planner):
    name = "rrtconnect-cost"
    label = "RRTConnect+Cost"
    unused_axes = ("sampler",)
    parametrizations = ("bspline",)

    def plan(self, ctx: Context, n_samples: int, seed: int, record_history: bool = False):
        ctx = ctx.to(self.device)  # a context made on the CPU plans on the planner's device
        from mpd.data.planning import plan_path

        gen = torch.Generator().manual_seed(seed)
        timer = Timer(self.device)
        hist: list[HistoryStep] | None = [] if record_history else None
        failures = 0
        with timer("total"):
            if ctx.q_goal is not None:
                goals = ctx.q_goal.expand(n_samples, -1)
            elif ctx.q_goal_ref is not None:
                goals = ctx.q_goal_ref.expand(n_samples, -1)
            else:
                from mpd.planners.goals import ik_goals

                with timer("ik"):
                    goals = ik_goals(self.task, self.env, ctx, n_samples, gen, restarts=self.settings.ik_restarts)
            paths = []
            qs = ctx.q_start.detach().cpu().double().numpy()
            for i in range(n_samples):
                qg = goals[i].detach().cpu().double().numpy()
                with timer("rrt"):
                    path = plan_path(
                        self.task,
                        self.env,
                        qs,
                        qg,
                        time_limit=self.settings.rrt_time_limit,
                        seed=seed * 1000 + i,
                    )
                if path is None:
                    failures += 1
                    path = np.linspace(qs, qg, self.param.n_points)
                paths.append(path)
            w = torch.as_tensor(self.param.fit(np.stack(paths)), dtype=torch.float32, device=self.device)
            x = self.normalizer.normalize(self.param.free_rows(w))
            if hist is not None:
                hist.append(HistoryStep("rrtconnect", 0, self.normalizer.unnormalize(x)))
            x = optimize_samples(self, x, ctx, timer, hist)
            free = self.normalizer.unnormalize(x)
        return self.finish(free, ctx, timer, hist, rrt_failures=failures)
