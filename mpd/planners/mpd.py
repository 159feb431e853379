"""MPD: cost-guided posterior sampling from the diffusion prior (the paper's Algorithm 2 with its DDIM adaptation).

Guidance acts only on the last denoising steps (``PlannerSettings.guided_steps``), in the model's unit-normalized
space of free control points. Two forms (``PlannerSettings.guided_update``):

* ``official`` (the authors' code): at a guided DDIM step t -> t', eps_theta(x_t) is evaluated once; M times,
  eps~ = lambda eps_theta + gamma clip(grad C(x_k)) and x_{k+1} = x_t + clip(DDIM_mean(x_k, eps~) - x_t, -delta,
  delta), where DDIM_mean is the DDIM update *without* its noise term (the first gradient at x_t itself). Then the
  step's noise sigma z is added once, after the M iterations and outside the clip (none into level 0 or with
  eta = 0): the delta budget is spent on the cost gradient only, and a guided step carries exactly the noise of an
  unguided one.
* ``paper``: the DDIM mean mu of (lambda eps_theta) is moved by M steps of gradient descent on C, each step
  clipped to mu +- delta; then the step's noise is added (none with eta = 0). The covariance factor of the
  Bayes-rule derivation is dropped, as the paper explains.

DDPM sampling (``sampler = "ddpm"``) uses the paper form around the DDPM posterior mean with the variance
pre-multiplied by alpha. With guidance off this planner is exactly Dprior (same code path, same random stream).
"""

from __future__ import annotations

import functools

import torch

from mpd.device import Arithmetic, resolve
from mpd.models.diffusion import ddim_sigma, ddim_step, ddim_timesteps, ddpm_mean, randn
from mpd.planners.base import Context, HistoryStep, Planner, Timer, model_context, register
from mpd.planners.optimize import clip_grad, optimize, project


@register
class MPD(Planner):
    name = "mpd"
    label = "MPD"
    model_kind = "diffusion"
    guided = True

    @property
    def arithmetic(self) -> Arithmetic:
        """The arithmetic the denoising network runs in here (``network_precision`` on the planner's device)."""
        return resolve(self.device, self.settings.network_precision, name="network_precision")

    def sample(self, ctx: Context, n: int, gen: torch.Generator, timer: Timer, hist: list | None) -> torch.Tensor:
        """n samples (normalized free rows) of the guided (or, for Dprior, unguided) denoising process."""
        s = self.settings
        net = self.model.network
        cond = self.model.normalize_context(model_context(ctx))
        shape = (n, self.param.n_free, self.task.dof)
        dev = self.device
        autocast = self.arithmetic.autocast
        grad_fn = self.cost_grad_fn(ctx, timer) if self.guided else None
        # the model's compiled U-Net (DiffusionModel.forward) when asked for; otherwise the network is called plainly
        eps_net = functools.partial(net, compiled=True) if s.network_compile else net
        if hasattr(net, "embed_context"):  # a DiffusionModel: every step's context embedding, computed once
            with timer("network"), autocast():
                cond = net.embed_context(cond)
        x = randn(shape, gen, dev)
        if hist is not None:
            hist.append(HistoryStep("noise", 0, self.normalizer.unnormalize(x)))

        def noise_if(sigma: float, t_next: int) -> torch.Tensor | None:
            return randn(shape, gen, dev) if sigma > 0 and t_next >= 1 else None

        if s.sampler == "ddim":
            pairs = ddim_timesteps(s.ddim_steps, s.ddim_schedule, net.n_diffusion_steps, s.ddim_variant, generator=gen)
            n_guided = s.guided_steps(len(pairs)) if self.guided else 0
            for i, (t, tn) in enumerate(pairs):
                with timer("network"), autocast():
                    eps = eps_net(x, t, cond).float()
                sigma = ddim_sigma(t, tn, s.eta) if tn >= 0 else 0.0
                if i < len(pairs) - n_guided:
                    x = ddim_step(x, eps, t, tn, s.eta, noise_if(sigma, tn))
                elif s.guided_update == "official":
                    x_t, xk = x, x
                    for _ in range(s.n_inner_steps):
                        eps_k = s.prior_weight * eps + s.guide_lr * clip_grad(grad_fn(xk), s.grad_clip)
                        xk = project(ddim_step(xk, eps_k, t, tn, s.eta, None), x_t, s.max_perturb)
                    z = noise_if(sigma, tn)
                    x = xk if z is None else xk + sigma * z
                else:
                    mean = ddim_step(x, s.prior_weight * eps, t, tn, s.eta, None)
                    x = optimize(mean, grad_fn, s.n_inner_steps, s.guide_lr, s.max_perturb, s.grad_clip)
                    z = noise_if(sigma, tn)
                    if z is not None:
                        x = x + sigma * z
                if hist is not None:
                    hist.append(HistoryStep("denoising", i + 1, self.normalizer.unnormalize(x)))
        else:
            sch = net.schedule
            steps = net.n_diffusion_steps
            n_guided = s.guided_steps(steps) if self.guided else 0
            for i, t in enumerate(range(steps - 1, -1, -1)):
                with timer("network"), autocast():
                    eps = eps_net(x, t, cond).float()
                guided = t < n_guided
                mean = ddpm_mean(x, s.ddpm_prior_weight * eps if guided else eps, t, schedule=sch)
                if guided:
                    mean = optimize(mean, grad_fn, s.ddpm_n_inner_steps, s.ddpm_guide_lr, s.max_perturb, s.grad_clip)
                std = (s.ddpm_variance_scale * float(sch.tables["posterior_variance"][t])) ** 0.5
                x = mean + std * randn(shape, gen, dev) if t > 0 and std > 0 else mean
                if hist is not None:
                    hist.append(HistoryStep("denoising", i + 1, self.normalizer.unnormalize(x)))
        return x

    def warmup(self, n_samples: int) -> float:
        """Compile the denoising network for batches of ``n_samples`` (the first plan of that size does it
        otherwise, inside its clock); returns the seconds it took (0 when the network is not compiled or is already
        compiled for that size). Inductor's on-disk cache makes the next process's warm-up a fraction of the first."""
        import time

        from mpd.models.context import context_shapes

        warm = self.__dict__.setdefault("_warm_sizes", set())
        net = getattr(self.model, "network", None)
        if not self.settings.network_compile or not hasattr(net, "embed_context") or n_samples in warm:
            return 0.0
        t0 = time.perf_counter()
        dev = self.device
        shapes = context_shapes(self.model.context_kind, self.task.dof)
        x = torch.zeros(n_samples, self.param.n_free, self.task.dof, device=dev)
        with torch.no_grad(), self.arithmetic.autocast():
            emb = net.embed_context({k: torch.zeros(1, *s, device=dev) for k, s in shapes.items()})
            net(x, net.n_diffusion_steps - 1, emb, compiled=True)
        warm.add(n_samples)
        return time.perf_counter() - t0

    def plan(self, ctx: Context, n_samples: int, seed: int, record_history: bool = False):
        ctx = ctx.to(self.device)  # a context made on the CPU plans on the planner's device
        # a CPU generator: the same random numbers whatever device the network runs on
        gen = torch.Generator().manual_seed(seed)
        timer = Timer(self.device)
        hist: list[HistoryStep] | None = [] if record_history else None
        with torch.no_grad(), timer("total"):
            x = self.sample(ctx, n_samples, gen, timer, hist)
            x = self.after_sampling(x, ctx, timer, hist)
            free = self.normalizer.unnormalize(x)
        timer.times["sampling"] = timer.times["total"] - timer.times.get("cost_gradient", 0.0)
        return self.finish(
            free, ctx, timer, hist, network_precision=self.arithmetic.dtype,
            network_compiled=self.settings.network_compile,
        )  # fmt: skip

    def after_sampling(self, x: torch.Tensor, ctx: Context, timer: Timer, hist: list | None) -> torch.Tensor:
        return x
