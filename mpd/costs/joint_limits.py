"""Joint-limit cost: 1/2 |violation|^2 of position, velocity and acceleration limits, each with margin eps.

The margin eps is taken off each limit in its own time units, as the authors' cost does: [q_min + eps, q_max - eps]
(rad), |qdot| <= qdot_max - eps (rad/s), |qddot| <= qddot_max - eps (rad/s^2). The velocity and acceleration
bounds are then scaled to the phase (q' = qdot T, q'' = qddot T^2): q'_max = (qdot_max - eps) T and q''_max =
(qddot_max - eps) T^2, so the margin is eps T and eps T^2 in phase units (not eps: that would be 10x / 100x smaller
in time units at T = 10 s). A value x is penalised outside its interval by the distance to it, v = x - clamp(x, lo,
hi), per point C = 1/2 (|v_q|^2 + |v_q'|^2 + |v_q''|^2), integrated over the phase. The velocity and acceleration
terms exist only where the robot defines those limits (the point mass does not).

Both presets use this form (the paper: 1/2 |.|^2 with margin eps). The authors' code reports 0.5 |v|_2 as the
value but steps along the squared form's gradient v; here the value is 1/2 |v|^2 so that value and gradient
agree. Their velocity term also penalises against the *position* limits (a bug, README "Paper vs code" 9);
here it uses the velocity limits.
"""

from __future__ import annotations

import torch

from mpd.costs.base import Cost, CostInput, CostTerm, register
from mpd.costs.phase_kernel import Penalty
from mpd.tasks import Task

MARGIN = 0.03  # eps of the authors' CostJointSpaceJointLimits (its class default; no config overrides it)


@register
class JointLimitsCost(Cost):
    name = "joint_limits"

    def __init__(self, task: Task, preset: str = "official", margin: float = MARGIN):
        super().__init__(task, preset)
        self.margin = float(margin)

    def _limits(self, x: torch.Tensor, duration: float) -> list[tuple[torch.Tensor, torch.Tensor] | None]:
        key = ("limits", duration, x.dtype, str(x.device))
        if key not in self._consts:
            r, e = self.robot, self.margin
            lims: dict[str, torch.Tensor] = {"q": torch.stack([r.q_min + e, r.q_max - e])}
            # the margin comes off in time units (rad/s, rad/s^2), then the bound is scaled to the phase
            if r.dq_max is not None:
                m = (r.dq_max - e) * duration
                lims["dq"] = torch.stack([-m, m])
            if r.ddq_max is not None:
                m = (r.ddq_max - e) * duration**2
                lims["ddq"] = torch.stack([-m, m])
            self._consts[key] = {k: v.to(dtype=x.dtype, device=x.device) for k, v in lims.items()}
        c = self._consts[key]
        return [None if k not in c else (c[k][0], c[k][1]) for k in ("q", "dq", "ddq")]

    def __call__(self, inp: CostInput, weight: float = 1.0) -> CostTerm:
        d = inp.dense
        w = self.weights(inp)
        value = torch.zeros(d.q.shape[0], dtype=d.q.dtype, device=d.q.device)
        grads = []
        for x, lim in zip((d.q, d.dq_ds, d.ddq_ds2), self._limits(d.q, d.duration)):
            if lim is None:
                grads.append(None)
                continue
            v = x - torch.clamp(x, lim[0], lim[1])
            value += (0.5 * v.square().sum(-1) * w).sum(-1)
            grads.append(v * (weight * w)[:, None])
        return CostTerm(value, *grads)

    def penalty(self, inp: CostInput) -> Penalty:
        """This cost for the fused pass (:mod:`mpd.costs.phase_kernel`)."""
        return Penalty(limits=tuple(self._limits(inp.dense.q, inp.dense.duration)))
