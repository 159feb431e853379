"""Dprior+Cost: sample the diffusion prior, then optimize the cost starting from the samples."""

from __future__ import annotations

from mpd.planners.base import register
from mpd.planners.mpd import MPD
from mpd.planners.prior_cost import optimize_samples


@register
class DiffusionPriorCost(MPD):
    name = "dprior-cost"
    label = "Dprior+Cost"
    guided = False

    def after_sampling(self, x, ctx, timer, hist):
        return optimize_samples(self, x, ctx, timer, hist)
