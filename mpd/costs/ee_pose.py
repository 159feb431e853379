"""End-effector goal-pose cost, on the last dense point q(1) only (no phase integral).

* ``official`` (the authors' CostTaskSpaceEEGoalPose): C = 1/2 |xi|^2, xi = log_SE3(T_goal T_ee^-1) = [v; w].
  Moving the joints moves T_ee by a spatial twist delta = J_s dq, T_ee <- exp(delta) T_ee, so
  E = T_goal T_ee^-1 <- E exp(-delta) and dC/dq = -J_s^T g(E), with g the gradient of 1/2 |log(E exp(eps))|^2
  (:func:`mpd.costs.se3.se3_half_sq_log_grad`). J_s is the *spatial* Jacobian, whose linear rows are
  v_s = pdot - w x p (the geometric Jacobian's are pdot), so J_s^T y = J_p^T y_v + J_w^T (y_w - p x y_v).
  The authors step along -J_s^T xi, the first-order approximation of that gradient: exact at the goal and for
  pure rotation or translation errors, off by O(|w| |v|) otherwise; we use the exact gradient so that value
  and gradient agree (see se3.py).
* ``paper``: C = 1/2 |p_goal - p_ee|^2 + 1/2 |Log(R_goal^T R_ee)|^2. Rotating the end effector by a
  world-frame increment d, R_ee <- Exp(d) R_ee, is the right perturbation R_goal^T R_ee Exp(R_ee^T d) of the
  relative rotation, whose log changes by J_r^-1(phi) R_ee^T d; with phi^T J_r^-1(phi) = phi^T the rotation
  gradient is R_ee phi, exactly.
"""

from __future__ import annotations

import torch

from mpd import kernels
from mpd.costs import ee_kernel
from mpd.costs.base import Cost, CostInput, CostTerm, register
from mpd.costs.se3 import cross, se3_half_sq_log_grad, se3_log, so3_log
from mpd.tasks import Task


def ee_pose_error(
    preset: str, pos: torch.Tensor, rot: torch.Tensor, goal_pos: torch.Tensor, goal_rot: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cost (B,) and its gradient w.r.t. the end-effector position (B, 3) and world-frame rotation (B, 3)."""
    if preset == "official":
        # E = T_goal T_ee^-1 = (R_g R_ee^T, p_g - R_g R_ee^T p_ee)
        R = goal_rot @ rot.transpose(-1, -2)
        t = goal_pos - (R @ pos[..., None])[..., 0]
        xi, parts = se3_log(R, t)
        y = -se3_half_sq_log_grad(parts)  # dC/d(spatial twist of T_ee), [v; w]
        y_v, y_w = y[..., :3], y[..., 3:]
        return 0.5 * xi.square().sum(-1), y_v, y_w - cross(pos, y_v)
    dp = pos - goal_pos
    phi, _ = so3_log(goal_rot.transpose(-1, -2) @ rot)
    value = 0.5 * dp.square().sum(-1) + 0.5 * phi.square().sum(-1)
    return value, dp, (rot @ phi[..., None])[..., 0]


@register
class EEPoseCost(Cost):
    name = "ee_pose"

    @classmethod
    def applicable(cls, task: Task) -> bool:
        return task.ee_goal

    def __call__(self, inp: CostInput, weight: float = 1.0) -> CostTerm:
        if inp.ee_goal is None:
            raise ValueError("the end-effector pose cost needs ee_goal=(position (B, 3), rotation (B, 3, 3))")
        q = inp.dense.q
        if kernels.active("ee_pose", q):
            kin, cols = inp.final_columns()
            if kin.frames_t is not None:  # one compiled pass (the torch lines below are its reference)
                goal_pos, goal_rot = (x.to(q.dtype) for x in inp.ee_goal)
                value, g_last = ee_kernel.ee_pass(self.robot.chain, kin, cols, goal_pos, goal_rot, self.preset, weight)
                g_q = torch.zeros_like(q)
                g_q[:, -1] = g_last
                return CostTerm(value, g_q=g_q)
        kin = inp.last_kinematics()
        goal_pos, goal_rot = (x.to(kin.ee_pos) for x in inp.ee_goal)
        value, g_pos, g_rot = ee_pose_error(self.preset, kin.ee_pos, kin.ee_rot, goal_pos, goal_rot)
        g_last = self.robot.ee_vjp(kin, weight * g_pos, weight * g_rot)  # (B, dof)
        g_q = torch.zeros_like(inp.dense.q)
        g_q[:, -1] = g_last
        return CostTerm(value, g_q=g_q)
