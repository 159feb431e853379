"""GPprior+Cost: the paper's uninformed baseline (essentially CHOMP), as the authors run it.

``gp_prior = "authors"`` (default, both presets; the authors' ``gp_prior`` branch of their inference code): a
Gaussian-process regressor over the phase s in [0, 1], zero prior mean, kernel ``c * RBF(l)``, fitted to the two end
points (q_start at s = 0, q_goal at s = 1) by maximum marginal likelihood with the length scale bounded below by
``||q_goal - q_start|| / 2`` (and above by 1e4; c in [1e-5, 1e5]), in raw joint units, one kernel shared by the
joints. The free control points are samples of its posterior at ``linspace(0, 1, n_free + 2)`` without the two ends.
They are then optimized in the normalized units of the other "+Cost" baselines (the data range the planner is given:
the runner passes the dataset's, as the authors' baselines use theirs) with the same routine and step count. Unlike
the authors' (``random_state=None``), the samples are seeded.

For two points the maximum-likelihood fit is closed form (no optimizer restarts needed): with a = q_start, b =
q_goal, D joints and k = exp(-1 / (2 l^2)) the kernel correlation between the ends, the likelihood profiled over c
is ``-D log(|a|^2 + |b|^2 - 2k a.b) + (D/2) log(1 - k^2)``, which increases for k < k* = 2 a.b / (|a|^2 + |b|^2)
and decreases after; so l* is l(k*) clipped to the bounds, and c* = S / (2D) with S = sum_d y_d^T R^-1 y_d. The
tests check the fit and the posterior against scikit-learn's ``GaussianProcessRegressor``.

``gp_prior = "bridge"`` (the earlier mpd variant): the mean puts the free control points on the straight line (at
their Greville phases, so the curve is the segment), the covariance is a squared-exponential kernel over phase
(``gp_lengthscale``) conditioned to vanish at both ends, scaled by ``gp_sigma`` in unit-normalized space.

With an end-effector goal the goal configuration is the one the context carries (``Context.q_goal_ref``, the
dataset's, as the authors do); only a context without one gets batched inverse kinematics, one solution per sample
from random restarts (different samples may then reach different goal configurations).
"""

from __future__ import annotations

import numpy as np
import torch

from mpd.planners.base import Context, HistoryStep, Planner, Timer, register
from mpd.planners.optimize import optimize

LENGTHSCALE_MAX = 1e4
CONSTANT_BOUNDS = (1e-5, 1e5)
GP_ALPHA = 1e-10  # scikit-learn's default jitter on the training covariance


def bridge_covariance(phases: np.ndarray, lengthscale: float) -> np.ndarray:
    """Squared-exponential covariance over ``phases`` conditioned on zero deviation at phase 0 and 1."""
    s = np.asarray(phases, dtype=np.float64)
    k = lambda a, b: np.exp(-((a[:, None] - b[None, :]) ** 2) / (2 * lengthscale**2))  # noqa: E731
    ends = np.array([0.0, 1.0])
    kxx, kxe, kee = k(s, s), k(s, ends), k(ends, ends)
    cov = kxx - kxe @ np.linalg.solve(kee, kxe.T)
    return (cov + cov.T) / 2


def fit_endpoint_gp(q_start: np.ndarray, q_goal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maximum-likelihood (constant c, length scale l) of ``c * RBF(l)`` on the points (0, q_start), (1, q_goal).

    Batched: ``q_start`` (dof,) or (B, dof), ``q_goal`` (B, dof) or (dof,) -> c (B,), l (B,) (scalars for 1-D input).
    """
    a, b = np.broadcast_arrays(np.asarray(q_start, np.float64), np.asarray(q_goal, np.float64))
    squeeze = a.ndim == 1
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    D = a.shape[-1]
    lower = np.maximum(np.linalg.norm(b - a, axis=-1) / 2, 1e-5)
    A, B, C = (a * a).sum(-1), (b * b).sum(-1), (a * b).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        k_star = np.where(A + B > 0, 2 * C / (A + B), 0.0)
        l_star = np.where((k_star > 0) & (k_star < 1), np.sqrt(-1.0 / (2 * np.log(k_star))), 0.0)
    l_star = np.where(k_star >= 1, LENGTHSCALE_MAX, l_star)
    ell = np.clip(l_star, lower, LENGTHSCALE_MAX)
    k = np.exp(-1.0 / (2 * ell**2))
    S = (A + B - 2 * k * C) / (1 - k * k)
    c = np.clip(S / (2 * D), *CONSTANT_BOUNDS)
    return (c[0], ell[0]) if squeeze else (c, ell)


def endpoint_gp_posterior(
    q_start: np.ndarray, q_goal: np.ndarray, phases: np.ndarray, c: np.ndarray, ell: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean (B, m, dof) and covariance (B, m, m) at ``phases`` of the zero-mean GP ``c * RBF(l)``
    conditioned on (0, q_start), (1, q_goal) (with scikit-learn's jitter ``GP_ALPHA``)."""
    a, b = np.broadcast_arrays(np.atleast_2d(np.asarray(q_start, np.float64)), np.atleast_2d(q_goal))
    c, ell = np.atleast_1d(c)[:, None, None], np.atleast_1d(ell)[:, None, None]
    s = np.asarray(phases, np.float64)
    ends = np.array([0.0, 1.0])
    rbf = lambda u, v: c * np.exp(-((u[:, None] - v[None, :]) ** 2)[None] / (2 * ell**2))  # noqa: E731
    kee = rbf(ends, ends) + GP_ALPHA * np.eye(2)
    kse = rbf(s, ends)  # (B, m, 2)
    w = np.linalg.solve(kee, kse.transpose(0, 2, 1)).transpose(0, 2, 1)  # K_se K_ee^-1
    y = np.stack([a, b], axis=1)  # (B, 2, dof)
    mean = w @ y
    cov = rbf(s, s) - w @ kse.transpose(0, 2, 1)
    return mean, (cov + cov.transpose(0, 2, 1)) / 2


@register
class GPPriorCost(Planner):
    name = "gp-cost"
    label = "GPprior+Cost"
    unused_axes = ("sampler",)
    parametrizations = ("bspline",)  # "all baselines use the B-spline parametrization"

    def _goal_configurations(self, ctx: Context, n: int, gen: torch.Generator, timer: Timer) -> torch.Tensor:
        if ctx.q_goal is not None:
            return ctx.q_goal.expand(n, -1)
        if ctx.q_goal_ref is not None:
            return ctx.q_goal_ref.to(ctx.q_start).expand(n, -1)
        from mpd.planners.goals import ik_goals

        with timer("ik"):
            return ik_goals(self.task, self.env, ctx, n, gen, restarts=self.settings.ik_restarts).to(ctx.q_start)

    def sample_prior(self, ctx: Context, n: int, gen: torch.Generator, timer: Timer) -> torch.Tensor:
        """n samples of the free rows (normalized)."""
        q_goal = self._goal_configurations(ctx, n, gen, timer)
        if self.settings.gp_prior == "bridge":
            return self._bridge_samples(ctx, q_goal, n, gen)
        qs = ctx.q_start.detach().cpu().double().numpy()
        qg = q_goal.detach().cpu().double().numpy()
        shared = bool(np.all(qg == qg[:1]))  # one goal for the whole batch: one fit
        goals = qg[:1] if shared else qg
        c, ell = fit_endpoint_gp(qs, goals)
        phases = np.linspace(0.0, 1.0, self.param.n_free + 2)[1:-1]
        mean, cov = endpoint_gp_posterior(qs, goals, phases, c, ell)
        m = len(phases)
        L = np.linalg.cholesky(cov + 1e-9 * np.maximum(c, 1.0)[:, None, None] * np.eye(m))
        z = torch.randn(n, m, self.task.dof, generator=gen, device=gen.device, dtype=torch.float64).cpu().numpy()
        raw = mean + L @ z  # (n, m, dof), broadcasting a shared fit over the batch
        free = torch.as_tensor(raw, dtype=ctx.q_start.dtype, device=ctx.q_start.device)
        return self.normalizer.normalize(free)

    def _bridge_samples(self, ctx: Context, q_goal: torch.Tensor, n: int, gen: torch.Generator) -> torch.Tensor:
        ph = self.param.param_phases()
        rows = self.param.a_free.argmax(0)  # the parameter row of each free row
        ph_free = ph[rows]
        qs = self.normalizer.normalize(ctx.q_start)[None, None, :]
        qg = self.normalizer.normalize(q_goal)[:, None, :]
        t = torch.as_tensor(ph_free, dtype=qs.dtype, device=qs.device)[None, :, None]
        mean = qs + t * (qg - qs)  # (n, n_free, dof)
        cov = bridge_covariance(ph_free, self.settings.gp_lengthscale)
        L = torch.as_tensor(np.linalg.cholesky(cov + 1e-9 * np.eye(len(ph_free))), dtype=qs.dtype, device=qs.device)
        z = torch.randn(n, len(ph_free), self.task.dof, generator=gen, device=gen.device).to(qs)
        x = mean + self.settings.gp_sigma * (L @ z)
        if self.param.ee_goal:  # the final configuration is the IK goal itself (zero deviation at phase 1)
            x[:, -1] = qg[:, 0]
        return x

    def plan(self, ctx: Context, n_samples: int, seed: int, record_history: bool = False):
        ctx = ctx.to(self.device)  # a context made on the CPU plans on the planner's device
        gen = torch.Generator().manual_seed(seed)
        timer = Timer(self.device)
        hist: list[HistoryStep] | None = [] if record_history else None
        s = self.settings
        with timer("total"):
            x0 = self.sample_prior(ctx, n_samples, gen, timer)
            if hist is not None:
                hist.append(HistoryStep("prior", 0, self.normalizer.unnormalize(x0)))
            cb = (
                None
                if hist is None
                else (lambda k, x: hist.append(HistoryStep("optimization", k + 1, self.normalizer.unnormalize(x))))
            )
            x = optimize(
                x0,
                self.cost_grad_fn(ctx, timer),
                s.opt_steps,
                s.opt_lr,
                s.opt_max_perturb,
                s.opt_grad_clip,
                cb,
            )
            free = self.normalizer.unnormalize(x)
        return self.finish(free, ctx, timer, hist)
