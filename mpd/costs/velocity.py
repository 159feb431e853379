"""Velocity cost: official 1/2 |q'(s)|_2 (the authors' configs), paper 1/2 |q'(s)|^2; phase integral."""

from __future__ import annotations

from mpd.costs.base import Cost, CostInput, CostTerm, register
from mpd.costs.phase_kernel import Penalty
from mpd.costs.smoothness import derivative_penalty


@register
class VelocityCost(Cost):
    name = "velocity"

    def __call__(self, inp: CostInput, weight: float = 1.0) -> CostTerm:
        value, g = derivative_penalty(inp.dense.dq_ds, self.weights(inp), weight, squared=self.preset == "paper")
        return CostTerm(value, g_dq=g)

    def penalty(self, inp: CostInput) -> Penalty:
        """This cost for the fused pass (:mod:`mpd.costs.phase_kernel`)."""
        return Penalty(norm_field=1, squared=self.preset == "paper")
