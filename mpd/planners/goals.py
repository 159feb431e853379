"""Goal configurations for planners that need one when the context gives an end-effector pose
(GPprior+Cost, RRTConnect+Cost, as in the paper: "we use a goal joint position computed with inverse kinematics")."""

from __future__ import annotations

import torch

from mpd.collision import CollisionChecker
from mpd.planners.base import Context


def ik_goals(task, env, ctx: Context, n: int, generator: torch.Generator, restarts: int = 4) -> torch.Tensor:
    """n goal configurations (n, dof) reaching the context's end-effector pose, collision free in ``env``.

    Each sample gets its own random restarts, so different samples may reach the pose with different
    configurations (the multimodality the paper's Fig. 8 shows). Samples whose IK failed reuse the successful
    solutions; if none succeeded, the closest configurations are returned (the planned batch will then be
    judged invalid by the evaluator, as it should).
    """
    from mpd.robots.ik import solve_ik

    checker = CollisionChecker(task, env=env)
    pos = ctx.ee_pos.detach().cpu().double()[None].expand(n, 3)
    rot = ctx.ee_rot.detach().cpu().double()[None].expand(n, 3, 3)
    res = solve_ik(
        task.robot,
        pos,
        rot,
        n_restarts=restarts,
        generator=generator,
        valid=lambda q: checker.configs(q).valid,
    )
    q = res.q
    ok = res.success
    if ok.any() and not ok.all():
        good = q[ok]
        fill = torch.arange(int((~ok).sum())) % len(good)
        q = q.clone()
        q[~ok] = good[fill]
    return q.to(device=ctx.q_start.device, dtype=ctx.q_start.dtype)
