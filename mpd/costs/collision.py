"""Environment collision cost: per point the sum over the robot spheres of ReLU(r + eps - sdf(c)), integrated.

eps is the task's ``collision.cost_margin`` in both presets (the paper gives no value; the authors' configs
add an extra inference margin to the dataset clearance, see the task files). The gradient w.r.t. a sphere
centre is -grad sdf(c) where the sphere is within the margin, mapped to the joints by the spheres' Jacobian
transpose; with the grid SDF it is the gradient stored at the nearest node (the paper's choice) or
interpolated (``trilinear``). When few (sphere, configuration) entries are active, only those enter the
Jacobian product (:func:`mpd.costs.base.spheres_vjp_sparse`).
"""

from __future__ import annotations

import numpy as np
import torch

from mpd import kernels
from mpd.costs import collision_kernel
from mpd.costs.base import Cost, CostInput, CostTerm, register, spheres_vjp_sparse
from mpd.costs.sdf import sdf_batch_last
from mpd.tasks import Task

# Above this share of active (sphere, configuration) entries the dense Jacobian product is the faster one. On the
# 2-core CPU (Panda, 100 x 128 points, one thread) both take the same time at ~7 %; the sparse product has serial
# parts (nonzero, index_add), so with two threads the dense one wins earlier.
SPARSE_FRACTION = 0.05


@register
class CollisionCost(Cost):
    name = "collision"

    def __init__(self, task: Task, preset: str = "official"):
        super().__init__(task, preset)
        self.margin = float(task.spec.collision.cost_margin)

    def __call__(self, inp: CostInput, weight: float = 1.0) -> CostTerm:
        B, n, dof = inp.shape
        kin = inp.kinematics()
        X = kin.points_t  # (S, 3, N)
        S, _, N = X.shape
        D = self.task.dim
        key = ("r", X.dtype, str(X.device))
        if key not in self._consts:
            self._consts[key] = {"r": (self.robot.sphere_radii + self.margin).to(X)[:, None]}
        w = self.weights(inp)
        if inp.sdf_mode == "nearest" and kernels.active("collision", X):
            # one compiled pass (the torch lines below are its reference)
            chain = self.robot.chain
            fkey = ("frames", X.dtype)
            if fkey not in self._consts:  # the frame of each sphere; the constant Jacobians of a translational chain
                jac = chain.points_jacobian()
                self._consts[fkey] = (
                    (np.ascontiguousarray(chain.point_joint + 1), chain.dof),
                    (None if jac is None else jac.astype(X.numpy().dtype)),
                )
            frames, jac = self._consts[fkey]
            if jac is not None:  # constant Jacobians (the point mass): the pass writes the joints' gradient
                per_config, _, _, g_q = collision_kernel.collision_pass(
                    inp.env, X, self._consts[key]["r"], w, weight, chain.reach, max_entries=0, jacobian=jac
                )
                return CostTerm(per_config.view(B, n).sum(-1), g_q=g_q.view(B, n, dof))
            # the frames' sums carry the gradient; the entries are only wanted for the sparse product
            cap = int(SPARSE_FRACTION * S * N)
            per_config, flat, rows, H = collision_kernel.collision_pass(
                inp.env, X, self._consts[key]["r"], w, weight, chain.reach, frames, cap
            )
            value = per_config.view(B, n).sum(-1)
            if flat is not None and flat.numel() <= SPARSE_FRACTION * S * N:
                g_q = spheres_vjp_sparse(self.robot, kin, flat, rows[:, :D], N)
            else:
                g_q = chain.vjp_from_forces(kin, H[:, 0], H[:, 1])
            return CostTerm(value, g_q=g_q.view(B, n, dof))
        d, g = sdf_batch_last(inp.env, X[:, :D], inp.sdf_mode, self.robot.chain.reach)
        a = self._consts[key]["r"] - d  # (S, N): depth inside the margin-inflated obstacles
        relu = a.clamp_min(0)
        value = (relu.sum(0).view(B, n) * w).sum(-1)
        n_active = int(torch.count_nonzero(relu))
        # the gradient w.r.t. a centre is -weight * (quadrature weight of its point) * grad sdf where active;
        # sign(relu) is the activity mask (torch.where with a (S, N) mask is 7x slower on CPU)
        cm = relu.sign_().mul_((-weight * w).repeat(B))  # (S, N)
        if n_active > SPARSE_FRACTION * S * N:
            G = X.new_empty(S, 3, N)
            torch.mul(cm[:, None], g, out=G[:, :D])
            if D < 3:
                G[:, D:] = 0
            g_q = self.robot.chain.points_vjp_frames(kin, G)
        else:
            cm = cm.reshape(-1)
            flat = cm.nonzero().squeeze(1)  # index s * N + configuration
            # (S, N, D) rows: for the grid a view of the gathered node rows, so only active entries are copied
            g_act = g.permute(0, 2, 1).reshape(S * N, D).index_select(0, flat)
            g_act *= cm.index_select(0, flat)[:, None]
            g_q = spheres_vjp_sparse(self.robot, kin, flat, g_act, N)
        return CostTerm(value, g_q=g_q.view(B, n, dof))
