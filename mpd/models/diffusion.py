"""Gaussian diffusion (DDPM, Ho et al. 2020) with epsilon prediction, and the DDPM / DDIM single-step updates.

Conventions (the authors'): N = 100 steps indexed t = 0 .. N-1, where t = 0 is the *first* noise level
(beta_0 > 0) and ``x_t = sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps``; cosine schedule (Nichol & Dhariwal 2021,
s = 0.008, betas clipped to [0, 0.999]). Every update predicts x_0 from eps and clips it to [-1, 1] (the data
are normalized to that box). The step functions are plain tensor maths so that cost-guided planners can call
them with a modified eps. A guided DDIM loop, in normalized space (``prior = mpd.models.load_model(...)``)::

    ctx = prior.normalize_context(raw_context)                      # batch 1, shared by all samples
    x = randn((n, prior.horizon, prior.dof), gen, prior.device)
    for t, t_next in ddim_timesteps(15, "quadratic", variant=..., generator=gen):
        with torch.no_grad():
            eps = prior.network(x, t, ctx)                          # eps_theta, once per step
        # guided steps: eps_tilde = lambda_prior * eps - gamma * clip(-grad_x C(x_k)), where the cost gradient
        # w.r.t. normalized x is prior.x_normalizer.grad_to_normalized(grad w.r.t. raw control points)
        noise = randn(x.shape, gen, prior.device) if t_next >= 1 and eta > 0 else None
        x = ddim_step(x, eps_tilde_or_eps, t, t_next, eta, noise)
    q_free = prior.x_normalizer.unnormalize(x)
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from typing import Literal

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from mpd.models.context import EE_GOAL, ContextEncoder
from mpd.models.unet import SinusoidalPosEmb, TemporalUnet, as_step_tensor, shared_step
from mpd.tasks.spec import ModelSpec

N_DIFFUSION_STEPS = 100

Sampler = Literal["ddim", "ddpm"]
StepSchedule = Literal["uniform", "quadratic"]
Variant = Literal["paper", "official"]


# --- noise schedule --------------------------------------------------------------------------------------
def cosine_betas(n_steps: int, s: float = 0.008) -> np.ndarray:
    """Betas of the cosine schedule: abar(t) = cos^2(((t/N) + s)/(1 + s) pi/2), normalized to abar(0) = 1."""
    x = np.linspace(0, n_steps, n_steps + 1, dtype=np.float64)
    abar = np.cos(((x / n_steps) + s) / (1 + s) * math.pi / 2) ** 2
    abar = abar / abar[0]
    return np.clip(1 - abar[1:] / abar[:-1], 0.0, 0.999)


class Schedule:
    """Per-step constants of the forward and reverse processes (float64, cast per dtype and device)."""

    def __init__(self, n_steps: int = N_DIFFUSION_STEPS):
        if n_steps < 2:
            raise ValueError(f"need at least 2 diffusion steps, got {n_steps}")
        self.n_steps = n_steps
        betas = cosine_betas(n_steps)
        alphas = 1 - betas
        abar = np.cumprod(alphas)
        abar_prev = np.concatenate([[1.0], abar[:-1]])
        self.tables: dict[str, np.ndarray] = {
            "betas": betas,
            "alphas_cumprod": abar,
            "alphas_cumprod_prev": abar_prev,
            # q(x_{t-1} | x_t, x_0) = N(c1 x_0 + c2 x_t, beta~_t I),
            # beta~_t = (1 - abar_{t-1}) / (1 - abar_t) beta_t
            "posterior_variance": betas * (1 - abar_prev) / (1 - abar),
            "posterior_mean_coef1": betas * np.sqrt(abar_prev) / (1 - abar),
            "posterior_mean_coef2": (1 - abar_prev) * np.sqrt(alphas) / (1 - abar),
        }
        self._cache: dict[tuple[str, torch.dtype, torch.device], torch.Tensor] = {}

    def table(self, name: str, like: torch.Tensor) -> torch.Tensor:
        key = (name, like.dtype, like.device)
        if key not in self._cache:
            self._cache[key] = torch.as_tensor(self.tables[name], dtype=like.dtype, device=like.device)
        return self._cache[key]

    def coef(self, name: str, t: int | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """Value at step t, broadcastable against ``like`` (scalar for an int t, else ``(B, 1, ...)``)."""
        if isinstance(t, int | np.integer):
            return self.table(name, like)[self.check_step(int(t))]
        t = t.to(like.device).long()
        if t.ndim == 0:
            return self.table(name, like)[t]
        return self.table(name, like)[t].reshape(-1, *([1] * (like.ndim - 1)))

    def abar(self, t: int) -> float:
        """abar_t as a Python float; abar_{-1} = 1 (the clean data)."""
        return 1.0 if t == -1 else float(self.tables["alphas_cumprod"][self.check_step(t)])

    def check_step(self, t: int) -> int:
        if not 0 <= t < self.n_steps:
            raise ValueError(f"diffusion step {t} is outside 0..{self.n_steps - 1}")
        return t


@functools.lru_cache(maxsize=8)
def get_schedule(n_steps: int = N_DIFFUSION_STEPS) -> Schedule:
    return Schedule(n_steps)


# --- single-step maths -----------------------------------------------------------------------------------
def q_sample(
    x0: torch.Tensor, t: int | torch.Tensor, noise: torch.Tensor, schedule: Schedule | None = None
) -> torch.Tensor:
    """Closed-form forward process: ``sqrt(abar_t) x0 + sqrt(1 - abar_t) noise``."""
    sch = schedule or get_schedule()
    abar = sch.coef("alphas_cumprod", t, x0)
    return abar.sqrt() * x0 + (1 - abar).sqrt() * noise


def predict_x0(
    x_t: torch.Tensor,
    eps: torch.Tensor,
    t: int | torch.Tensor,
    clip: bool = True,
    schedule: Schedule | None = None,
) -> torch.Tensor:
    """``x0 = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t)``, clipped to [-1, 1] by default."""
    sch = schedule or get_schedule()
    abar = sch.coef("alphas_cumprod", t, x_t)
    x0 = (x_t - (1 - abar).sqrt() * eps) / abar.sqrt()
    return x0.clamp(-1.0, 1.0) if clip else x0


def ddpm_mean(
    x_t: torch.Tensor,
    eps: torch.Tensor,
    t: int | torch.Tensor,
    clip: bool = True,
    schedule: Schedule | None = None,
) -> torch.Tensor:
    """Posterior mean mu_theta(x_t, t) via the (clipped) x0 prediction. Without clipping this equals the
    paper's eq. (ddpm_posterior_mean), ``(x_t - beta_t / sqrt(1 - abar_t) eps) / sqrt(alpha_t)``."""
    sch = schedule or get_schedule()
    x0 = predict_x0(x_t, eps, t, clip, sch)
    return sch.coef("posterior_mean_coef1", t, x_t) * x0 + sch.coef("posterior_mean_coef2", t, x_t) * x_t


def ddpm_step(
    x_t: torch.Tensor,
    eps: torch.Tensor,
    t: int,
    noise: torch.Tensor | None,
    variance_scale: float = 1.0,
    *,
    clip: bool = True,
    schedule: Schedule | None = None,
) -> torch.Tensor:
    """One reverse DDPM step x_t -> x_{t-1} = mu_theta + sqrt(alpha * beta~_t) noise.

    ``variance_scale`` is the paper's alpha in [0, 1] (0: the mean only, 1: DDPM). No noise is added at t = 0,
    whose output is the (clipped) x0 prediction itself.
    """
    sch = schedule or get_schedule()
    mean = ddpm_mean(x_t, eps, t, clip, sch)
    if t == 0 or noise is None or variance_scale == 0:
        return mean
    return mean + math.sqrt(variance_scale * float(sch.tables["posterior_variance"][t])) * noise


def ddim_sigma(t: int, t_next: int, eta: float, schedule: Schedule | None = None) -> float:
    """``eta * sqrt((1 - abar_next) / (1 - abar_t)) * sqrt(1 - abar_t / abar_next)``; eta = 1 gives DDPM's
    posterior standard deviation for consecutive steps."""
    sch = schedule or get_schedule()
    a_t, a_next = sch.abar(t), sch.abar(t_next)
    return eta * math.sqrt(max((1 - a_next) / (1 - a_t) * (1 - a_t / a_next), 0.0))


def ddim_step(
    x_t: torch.Tensor,
    eps: torch.Tensor,
    t: int,
    t_next: int,
    eta: float = 0.0,
    noise: torch.Tensor | None = None,
    *,
    clip: bool = True,
    schedule: Schedule | None = None,
) -> torch.Tensor:
    """One DDIM step (Song et al. 2021) from step t to step ``t_next`` < t; ``t_next = -1`` means "to x0".

    ``x_next = sqrt(abar_next) x0 + sqrt(1 - abar_next - sigma^2) eps + sigma noise`` with
    ``x0 = clip(predict_x0(x_t, eps, t))`` and sigma from :func:`ddim_sigma`. Noise is added only when
    ``t_next >= 1`` (as the authors: none on the step into level 0); ``t_next = -1`` returns x0.
    A cost-guided planner passes its modified eps (e.g. ``lambda_prior * eps_theta - gamma * g``) here.
    """
    sch = schedule or get_schedule()
    if not -1 <= t_next < t:
        raise ValueError(f"DDIM step needs -1 <= t_next < t, got t={t}, t_next={t_next}")
    x0 = predict_x0(x_t, eps, t, clip, sch)
    if t_next == -1:
        return x0
    a_next = sch.abar(t_next)
    sigma = ddim_sigma(t, t_next, eta, sch)
    x_next = math.sqrt(a_next) * x0 + math.sqrt(max(1 - a_next - sigma**2, 0.0)) * eps
    if t_next >= 1 and sigma > 0 and noise is not None:
        x_next = x_next + sigma * noise
    return x_next


def sampler_grid(
    n_steps: int = 15, schedule: StepSchedule = "quadratic", n_train: int = N_DIFFUSION_STEPS
) -> torch.Tensor:
    """The distinct steps a DDIM run of ``n_steps`` visits: the ``paper`` variant's (quadratic/15: 0, 1, 2, 4, 7, ...,
    77, 90), which hold all of the ``official`` variant's fixed steps (it adds one random step per call)."""
    pairs = ddim_timesteps(n_steps, schedule, n_train, "paper")
    return torch.tensor(sorted(t for t, _ in pairs), dtype=torch.long)


def ddim_timesteps(
    n_steps: int,
    schedule: StepSchedule = "quadratic",
    n_train: int = N_DIFFUSION_STEPS,
    variant: Variant = "paper",
    generator: torch.Generator | None = None,
) -> list[tuple[int, int]]:
    """The (t, t_next) pairs of a DDIM run, in the order they are applied; ``t_next = -1`` means "to x0".

    Grid: ``uniform`` = floor(linspace(0, n_train - 1, n_steps)); ``quadratic`` =
    floor(linspace(0, sqrt(0.9 n_train), n_steps)^2), which for 15 of 100 steps is
    [0, 0, 1, 4, 7, 11, 16, 22, 29, 37, 45, 55, 66, 77, 90] (more steps near the data end).

    * ``variant="paper"``: deterministic, ``n_steps`` distinct steps: duplicates are bumped up
      (t_k = max(t_k, t_{k-1} + 1)), run in descending order, the last one going to x0: n_steps network calls.
      Quadratic/15: 90, 77, ..., 4, 2, 1, 0 -> x0.
    * ``variant="official"``: the authors' code. Duplicates are removed and as many random *unused* steps of
      0..n_train-1 are added (one for quadratic/15), drawn from ``generator`` on every call; descending order;
      the final pair (0, -1) is replaced by (1, 0), so the step 1 -> 0 is done twice and the run ends at level
      0 (not at the x0 prediction). Also n_steps network calls.
    """
    if not 1 <= n_steps <= n_train:
        raise ValueError(f"DDIM steps must be in 1..{n_train}, got {n_steps}")
    if schedule == "uniform":
        grid = np.floor(np.linspace(0, n_train - 1, n_steps)).astype(int)
    elif schedule == "quadratic":
        grid = np.floor(np.linspace(0, math.sqrt(0.9 * n_train), n_steps) ** 2).astype(int)
    else:
        raise ValueError(f"unknown DDIM schedule {schedule!r} (uniform, quadratic)")
    if variant == "paper":
        steps = [int(grid[0])]
        for t in grid[1:]:
            steps.append(max(int(t), steps[-1] + 1))
        if steps[-1] >= n_train:
            raise ValueError(f"{n_steps} distinct {schedule} DDIM steps do not fit in 0..{n_train - 1}")
        seq = steps[::-1]
        return list(zip(seq, seq[1:] + [-1]))
    if variant == "official":
        used = set(grid.tolist())
        unique = sorted(used)
        n_extra = n_steps - len(unique)
        if n_extra:
            unused = torch.tensor([t for t in range(n_train) if t not in used])
            dev = generator.device if generator is not None else "cpu"
            pick = torch.randperm(len(unused), generator=generator, device=dev)[:n_extra].cpu()
            unique = sorted(unique + unused[pick].tolist())
        seq = unique[::-1]
        pairs = list(zip(seq, seq[1:] + [-1]))
        if n_steps > 1:  # with a single step there is no (1, 0) to repeat: that run is just t -> x0
            pairs[-1] = (1, 0)
        return pairs
    raise ValueError(f"unknown DDIM variant {variant!r} (paper, official)")


# --- randomness ------------------------------------------------------------------------------------------
def randn(
    shape: tuple[int, ...],
    generator: torch.Generator | None,
    device: torch.device | str,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Standard normal noise on ``device``. Drawn on the generator's own device and moved, so a CPU generator
    gives the same numbers whatever device the model runs on."""
    device = torch.device(device)
    if generator is None:
        return torch.randn(shape, device=device, dtype=dtype)
    return torch.randn(shape, generator=generator, device=generator.device, dtype=dtype).to(device)


def randint(
    high: int, shape: tuple[int, ...], generator: torch.Generator | None, device: torch.device | str
) -> torch.Tensor:
    device = torch.device(device)
    if generator is None:
        return torch.randint(high, shape, device=device)
    return torch.randint(high, shape, generator=generator, device=generator.device).to(device)


# --- the model -------------------------------------------------------------------------------------------
class GoalHead(nn.Module):
    """A correction to the predicted noise of the last row (an end-effector-goal task's free final configuration):
    an MLP (three hidden Mish layers of ``width``) of [that row's noisy values, a sinusoidal embedding of the step,
    the context embedding]. Its output layer starts at zero, so an untrained head leaves the U-Net's prediction as
    it is. Not in the paper (ModelSpec.goal_head_width)."""

    def __init__(self, dof: int, context_dim: int, time_emb_dim: int, width: int):
        super().__init__()
        self.time_emb = SinusoidalPosEmb(time_emb_dim)
        self.net = nn.Sequential(
            nn.Linear(dof + time_emb_dim + context_dim, width),
            nn.Mish(),
            nn.Linear(width, width),
            nn.Mish(),
            nn.Linear(width, width),
            nn.Mish(),
            nn.Linear(width, dof),
        )
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, x_last: torch.Tensor, t: torch.Tensor, context_emb: torch.Tensor) -> torch.Tensor:
        """``(B, d)`` noisy final rows, ``(B,)`` steps, ``(B, context_dim)`` -> ``(B, d)``."""
        return self.net(torch.cat([x_last, self.time_emb(t).to(x_last.dtype), context_emb], dim=-1))


class DiffusionModel(nn.Module):
    """eps_theta(x_t, t, c): context encoder + temporal U-Net; inputs and outputs in normalized space."""

    def __init__(
        self,
        dof: int,
        horizon: int,
        context_kind: str,
        spec: ModelSpec,
        n_diffusion_steps: int = N_DIFFUSION_STEPS,
    ):
        super().__init__()
        self.dof = dof
        self.horizon = horizon
        self.context_kind = context_kind
        self.schedule = get_schedule(n_diffusion_steps)
        self.context_encoder = ContextEncoder(
            context_kind, dof, spec.context_dim, spec.context_layers, spec.context_init
        )
        self.unet = TemporalUnet(dof, spec.context_dim, spec.unet_dim, spec.unet_dim_mults, spec.time_emb_dim)
        self.goal_head = None
        if spec.goal_head_width:
            if context_kind != EE_GOAL:
                raise ValueError(
                    f"model.goal_head_width = {spec.goal_head_width}: a goal head needs an end-effector-goal task "
                    f"(the last row is then the free final configuration); this context is {context_kind!r}"
                )
            self.goal_head = GoalHead(dof, spec.context_dim, spec.time_emb_dim, spec.goal_head_width)

    @property
    def n_diffusion_steps(self) -> int:
        return self.schedule.n_steps

    def embed_context(self, context: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The context's embedding (rows, context_dim), which :meth:`forward` also takes in place of the fields: the
        steps of one denoising process share it (a planner computes it once, not at every step)."""
        return self.context_encoder(context)

    def forward(
        self,
        x_t: torch.Tensor,
        t: int | torch.Tensor,
        context: Mapping[str, torch.Tensor] | torch.Tensor,
        compiled: bool = False,
    ) -> torch.Tensor:
        """Predicted noise. Context fields have batch 1 (shared by every sample) or the batch of ``x_t``; a tensor is
        their embedding (:meth:`embed_context`). ``compiled``: the U-Net through :meth:`TemporalUnet.compiled`
        (inference only, under ``torch.no_grad()``)."""
        emb = context if isinstance(context, torch.Tensor) else self.context_encoder(context)
        if compiled:
            if torch.is_grad_enabled():
                raise RuntimeError("the compiled network is for inference: call it under torch.no_grad()")
            try:
                rows = 1 if len(emb) == 1 and shared_step(t) else x_t.shape[0]  # the step as a tensor, not a constant
                eps = self.unet.compiled()(x_t, as_step_tensor(t, rows, x_t.device), emb)
            except torch._dynamo.exc.BackendCompilerFailed as e:
                raise RuntimeError(
                    "planner.network_compile: torch.compile could not compile the denoising network (on a CPU "
                    f"inductor needs a C++ compiler, e.g. g++); run with network_compile = false. Cause: {e}"
                ) from e
        else:
            eps = self.unet(x_t, t, emb)
        if self.goal_head is None:
            return eps
        b = x_t.shape[0]
        head = self.goal_head(
            x_t[:, -1, :], as_step_tensor(t, b, x_t.device), emb.expand(b, -1) if len(emb) == 1 else emb
        )
        return torch.cat([eps[:, :-1], eps[:, -1:] + head[:, None].to(eps.dtype)], dim=1)

    def loss(
        self,
        x0: torch.Tensor,
        context: Mapping[str, torch.Tensor],
        generator: torch.Generator | None = None,
        weighting: Literal["uniform", "min_snr"] = "uniform",
        min_snr_gamma: float = 5.0,
        t_grid: torch.Tensor | None = None,
        t_grid_fraction: float = 0.0,
        goal_row_weight: float = 1.0,
    ) -> torch.Tensor:
        """MSE between the true and the predicted noise, t ~ U{0..N-1}; with ``weighting="min_snr"`` each sample's
        squared error is weighted by ``min(SNR_t, gamma) / SNR_t``, SNR_t = abar_t / (1 - abar_t) (Hang et al.
        2023, the epsilon form). The random draws are the same for both weightings.

        ``t_grid`` (steps, e.g. :func:`sampler_grid`) with ``t_grid_fraction`` = p: each sample's step is drawn
        uniformly from the grid with probability p, else from U{0..N-1}, i.e. t ~ p U(grid) + (1 - p) U{0..N-1}:
        a short training spends its samples on the levels the sampler visits. The uniform draws come first, so
        the uniform part's stream is the one of a plain run; the grid adds two draws after the noise.

        ``goal_row_weight`` = w: the squared errors are averaged over rows with weight w for the last row (the free
        final configuration of an end-effector-goal task) and 1 for the others, i.e. divided by the weights' sum;
        w = 1 is the plain mean."""
        t, noise = self.loss_draws(x0, generator, t_grid, t_grid_fraction)
        return self.loss_of_draws(x0, context, t, noise, weighting, min_snr_gamma, goal_row_weight)

    def loss_draws(
        self,
        x0: torch.Tensor,
        generator: torch.Generator | None = None,
        t_grid: torch.Tensor | None = None,
        t_grid_fraction: float = 0.0,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The random part of :meth:`loss`: each sample's step ``t`` and noise, drawn from ``generator`` in the
        loss's order (a compiled training step draws them eagerly and compiles :meth:`loss_of_draws`)."""
        b = x0.shape[0]
        t = randint(self.n_diffusion_steps, (b,), generator, x0.device)
        noise = randn(tuple(x0.shape), generator, x0.device, x0.dtype)
        if t_grid is not None and t_grid_fraction > 0:
            grid = t_grid.to(x0.device)
            pick = grid[randint(len(grid), (b,), generator, x0.device)]
            u = torch.rand((b,), generator=generator, device=generator.device if generator is not None else "cpu")
            t = torch.where(u.to(x0.device) < t_grid_fraction, pick, t)
        return t, noise

    def loss_of_draws(
        self,
        x0: torch.Tensor,
        context: Mapping[str, torch.Tensor],
        t: torch.Tensor,
        noise: torch.Tensor,
        weighting: Literal["uniform", "min_snr"] = "uniform",
        min_snr_gamma: float = 5.0,
        goal_row_weight: float = 1.0,
    ) -> torch.Tensor:
        """The deterministic part of :meth:`loss`, given its draws (:meth:`loss_draws`)."""
        if weighting not in ("uniform", "min_snr"):
            raise ValueError(f"unknown loss weighting {weighting!r} (known: uniform, min_snr)")
        pred = self(q_sample(x0, t, noise, self.schedule), t, context)
        if weighting == "uniform" and goal_row_weight == 1.0:
            return F.mse_loss(pred.float(), noise)
        sq = (pred.float() - noise).pow(2)  # (b, H, d)
        if goal_row_weight != 1.0:
            rows = torch.ones(sq.shape[1], device=sq.device, dtype=sq.dtype)
            rows[-1] = goal_row_weight
            per_sample = (sq.mean(2) * rows).sum(1) / rows.sum()
        else:
            per_sample = sq.flatten(1).mean(1)
        if weighting == "uniform":
            return per_sample.mean()
        abar = self.schedule.table("alphas_cumprod", x0)[t]
        snr = abar / (1 - abar)
        return (snr.clamp(max=min_snr_gamma) / snr * per_sample).mean()

    def sample(self, context: Mapping[str, torch.Tensor], n: int, **kwargs) -> torch.Tensor | tuple:
        """Unguided samples (normalized space); keywords as :func:`sample`."""
        return sample(self, context, n, **kwargs)


EpsModel = Callable[[torch.Tensor, int, Mapping[str, torch.Tensor]], torch.Tensor]


@torch.no_grad()
def sample(
    model: EpsModel,
    context: Mapping[str, torch.Tensor],
    n: int,
    *,
    sampler: Sampler = "ddim",
    steps: int = 15,
    schedule: StepSchedule = "quadratic",
    variant: Variant = "paper",
    eta: float = 0.0,
    variance_scale: float = 1.0,
    generator: torch.Generator | None = None,
    return_history: bool = False,
    clip: bool = True,
    shape: tuple[int, int] | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor | tuple[torch.Tensor, list[torch.Tensor]]:
    """Plain (unguided) samples ``(n, H, d)`` from the prior in normalized space.

    ``model(x_t, t, context)`` predicts the noise; ``context`` holds one context (batch 1) or n. The initial
    noise and every step's noise come from ``generator`` in a fixed order, so a seeded generator gives the
    same samples. ``sampler="ddpm"`` runs all N steps with :func:`ddpm_step` (``variance_scale`` = alpha);
    ``"ddim"`` runs :func:`ddim_timesteps` (``steps``, ``schedule``, ``variant``) with :func:`ddim_step`
    (``eta``). With ``return_history`` also returns the list of x after each step, starting with the noise.
    ``shape`` (H, d) defaults to ``(model.horizon, model.dof)``.
    """
    horizon, dof = shape if shape is not None else (model.horizon, model.dof)  # type: ignore[attr-defined]
    if device is None:
        first = next(iter(context.values()), None)
        device = first.device if first is not None else torch.device("cpu")
    sch = getattr(model, "schedule", None) or get_schedule()
    x = randn((n, horizon, dof), generator, device)
    history = [x]
    if sampler == "ddpm":
        for t in range(sch.n_steps - 1, -1, -1):
            eps = model(x, t, context)
            noise = randn(tuple(x.shape), generator, device) if t > 0 and variance_scale > 0 else None
            x = ddpm_step(x, eps, t, noise, variance_scale, clip=clip, schedule=sch)
            history.append(x)
    elif sampler == "ddim":
        for t, t_next in ddim_timesteps(steps, schedule, sch.n_steps, variant, generator):
            eps = model(x, t, context)
            noise = randn(tuple(x.shape), generator, device) if t_next >= 1 and eta > 0 else None
            x = ddim_step(x, eps, t, t_next, eta, noise, clip=clip, schedule=sch)
            history.append(x)
    else:
        raise ValueError(f"unknown sampler {sampler!r} (ddim, ddpm)")
    return (x, history) if return_history else x
