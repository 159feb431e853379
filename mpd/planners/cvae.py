"""CVAE: samples of the conditional VAE baseline (same U-Net backbone, 32-D latent)."""

from __future__ import annotations

import torch

from mpd.planners.base import Context, HistoryStep, Planner, Timer, model_context, register


@register
class CVAEPrior(Planner):
    name = "cvae"
    label = "CVAE"
    model_kind = "cvae"
    uses_cost = False
    unused_axes = ("sampler",)

    def after_sampling(self, x: torch.Tensor, ctx: Context, timer: Timer, hist: list | None) -> torch.Tensor:
        return x

    def plan(self, ctx: Context, n_samples: int, seed: int, record_history: bool = False):
        ctx = ctx.to(self.device)  # a context made on the CPU plans on the planner's device
        gen = torch.Generator().manual_seed(seed)
        timer = Timer(self.device)
        hist: list[HistoryStep] | None = [] if record_history else None
        with torch.no_grad(), timer("total"):
            with timer("network"):
                x = self.model.sample(model_context(ctx), n_samples, generator=gen, normalized=True)
            if hist is not None:
                hist.append(HistoryStep("prior", 0, self.normalizer.unnormalize(x)))
            x = self.after_sampling(x, ctx, timer, hist)
            free = self.normalizer.unnormalize(x)
        timer.times["sampling"] = timer.times["total"] - timer.times.get("cost_gradient", 0.0)
        return self.finish(free, ctx, timer, hist)
