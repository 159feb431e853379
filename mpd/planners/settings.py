"""Planner hyperparameters and the two named presets.

``official`` (the default) follows the authors' inference configs, which produced the published results;
``paper`` follows the paper's text (Algorithm 2, appendix B). Where they differ
(``docs/PAPER_VS_CODE.md``, "Paper vs code" 1-3, 6, 17):

- guided DDIM steps: official ceil(task guide_fraction x 15) = 5 or 3; paper the last i_cost = 3.
- DDIM eta: official 0.5 (stochastic); paper 0 (deterministic).
- quadratic schedule: official replaces the duplicate 0 by a random unused step on each call and does the final
  1 -> 0 step twice; paper 15 distinct steps.
- guided update: official eps~ = lambda eps - gamma clip(-grad C, -1, 1), the DDIM update re-applied to the
  iterate M times, each clipped to x_t +- delta; paper M gradient steps on the DDIM mean mu (of lambda eps),
  clipped to mu +- delta.
- cost gradient clipping: official value clip to [-1, 1]; paper none.
- cost forms and weights: official task `[costs.weights]`, norms for velocity/acceleration; paper
  `[costs.paper_weights]`, squared norms.
- "+Cost" baselines: official 12 steps, lr 0.01, grad clip 1, delta 0.15; paper 12 steps (= i_cost x M),
  lr = gamma, no clip, delta 0.15.

Every field can be overridden per task (``[inference]`` in the task file) and per run (a spec axis such as
``planner.guide_lr``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

PRESETS = ("official", "paper")

# The fast path of the diffusion network, the default of the Python API and of spec runs: compiled (inductor), in
# bf16 where the device computes it natively (fp32 elsewhere). Planner settings or a spec's planner.network_* axes
# override it; the environment variable MPD_COMPILE=0 (or false/no/off) turns it off: the eager fp32 network.
FAST_SETTINGS = {"network_compile": True, "network_precision": "auto"}


def fast_enabled(device=None) -> bool:
    """Whether the fast path is the default: not when the environment asks for the eager network
    (``MPD_COMPILE=0``), nor on a ``device`` torch.compile cannot build kernels for (a CPU without a C++ compiler)."""
    import os

    if os.environ.get("MPD_COMPILE", "1").strip().lower() in ("0", "false", "no", "off"):
        return False
    if device is None:
        return True
    from mpd.device import can_compile

    return can_compile(device)


@dataclass(frozen=True)
class PlannerSettings:
    preset: Literal["official", "paper"] = "official"
    # -- diffusion sampling ----------------------------------------------------------------------------------
    sampler: Literal["ddim", "ddpm"] = "ddim"
    ddim_steps: int = 15
    # the denoising network's forward passes: fp32, bf16 autocast, or auto (bf16 where the device computes it
    # natively: AVX512_BF16 / AMX CPUs, CUDA; fp32 elsewhere). Recorded per results row (info_network_precision).
    network_precision: Literal["fp32", "bf16", "auto"] = "fp32"
    # the U-Net's forward compiled by torch.compile (inductor, frozen weights) for the denoising passes: faster per
    # pass, but each new batch shape compiles first (~30-70 s on a 2-core CPU), so it pays off over many plans of
    # one process. Recorded per results row (info_network_compiled).
    network_compile: bool = False
    ddim_schedule: Literal["quadratic", "uniform"] = "quadratic"
    ddim_variant: Literal["official", "paper"] = "official"
    eta: float = 0.5
    ddpm_variance_scale: float = 0.49  # alpha; the authors' (untuned) DDPM config scales the noise std by 0.7
    # -- cost guidance (MPD) -----------------------------------------------------------------------------------
    guide_fraction: float | None = 0.3  # guided steps = ceil(fraction x steps); None -> use n_guided_steps
    n_guided_steps: int = 3  # i_cost, used when guide_fraction is None
    n_inner_steps: int = 4  # M
    prior_weight: float = 0.25  # lambda_prior
    guide_lr: float = 1.0  # gamma
    max_perturb: float = 0.15  # delta, in unit-normalized control-point space
    grad_clip: float | None = 1.0  # element-wise value clip of the cost gradient (None: off)
    guided_update: Literal["official", "paper"] = "official"
    # DDPM guidance (the authors' "ddpm_not_tuned" config)
    ddpm_guide_fraction: float = 0.2
    ddpm_prior_weight: float = 0.95
    ddpm_n_inner_steps: int = 2
    ddpm_guide_lr: float = 0.01
    # -- "+Cost" baselines: gradient steps after sampling ------------------------------------------------------
    opt_steps: int = 12
    opt_lr: float = 0.01
    opt_max_perturb: float = 0.15
    opt_grad_clip: float | None = 1.0
    # -- costs ---------------------------------------------------------------------------------------------------
    cost_preset: Literal["official", "paper"] = "official"
    # the collision cost's SDF lookup: the nearest node of mpd's grid (the paper's "nearest point in the grid"), the
    # trilinear interpolation, the exact SDF, or "authors": the authors' grid read with their off-by-one index (value
    # and gradient of one node; a measurement of their cost field, reports/cost-grid-authors)
    sdf_mode: Literal["nearest", "trilinear", "analytic", "authors"] = "nearest"
    # -- GP prior (GPprior+Cost) ------------------------------------------------------------------------------------
    gp_prior: Literal["authors", "bridge"] = "authors"  # the authors' end-point GP regressor, or mpd's earlier bridge
    gp_sigma: float = 0.3  # bridge only: prior std of the free control points, unit-normalized space
    gp_lengthscale: float = 0.25  # bridge only: in phase units
    # -- RRTConnect (+Cost) -------------------------------------------------------------------------------------------
    rrt_time_limit: float = 10.0
    # -- inverse kinematics for planners that need a goal configuration (GPprior+Cost, RRTConnect+Cost) ---------------
    ik_restarts: int = 4

    def guided_steps(self, n_steps: int) -> int:
        """How many of the last denoising steps are cost-guided."""
        if self.sampler == "ddpm":
            return math.ceil(self.ddpm_guide_fraction * n_steps)
        if self.guide_fraction is None:
            return min(self.n_guided_steps, n_steps)
        return math.ceil(round(self.guide_fraction * n_steps, 9))

    def replace(self, **kw) -> PlannerSettings:
        from mpd.planners.validation import check_settings  # type and range of every field (one-line errors)

        return dataclasses.replace(self, **check_settings(kw))


PAPER_OVERRIDES = {
    "preset": "paper",
    "ddim_variant": "paper",
    "eta": 0.0,
    "guide_fraction": None,
    "n_guided_steps": 3,
    "grad_clip": None,
    "guided_update": "paper",
    "opt_lr": 1.0,
    "opt_grad_clip": None,
    "cost_preset": "paper",
}


def planner_settings(task, preset: str = "official", **overrides) -> PlannerSettings:
    """Settings of a preset for a task (the task's ``[inference]`` applies to ``official``), then overrides."""
    if preset not in PRESETS:
        raise ValueError(f"unknown planner preset {preset!r} (known: {', '.join(PRESETS)})")
    s = PlannerSettings()
    if preset == "official":
        s = s.replace(
            guide_fraction=task.spec.inference.guide_fraction,
            rrt_time_limit=task.spec.data.planner_time_limit,
        )
    else:
        s = s.replace(**PAPER_OVERRIDES, rrt_time_limit=task.spec.data.planner_time_limit)
    return s.replace(**overrides) if overrides else s
