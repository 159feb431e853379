"""CVAE+Cost: sample the CVAE, then optimize the cost starting from the samples."""

from __future__ import annotations

from mpd.planners.base import register
from mpd.planners.cvae import CVAEPrior
from mpd.planners.prior_cost import optimize_samples


@register
class CVAEPriorCost(CVAEPrior):
    name = "cvae-cost"
    label = "CVAE+Cost"
    uses_cost = True

    def after_sampling(self, x, ctx, timer, hist):
        return optimize_samples(self, x, ctx, timer, hist)
