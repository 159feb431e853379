"""Dprior: samples of the diffusion prior alone (MPD with guidance off: the same code path and random stream)."""

from __future__ import annotations

from mpd.planners.base import register
from mpd.planners.mpd import MPD


@register
class DiffusionPrior(MPD):
    name = "dprior"
    label = "Dprior"
    guided = False
    uses_cost = False
