"""Conditional VAE baseline (paper, "Baselines") on the temporal U-Net backbone, as the authors build and train it.

Encoder q(z | x, c): the U-Net down path and one mid block on x, FiLM-conditioned on the context embedding; the
flattened bottleneck goes through one linear layer to the mean and log-variance of a 32-D Gaussian. The
log-variance is soft-clipped to [-7, 2] with the differentiable two-softplus clamp the authors use
(``lo + softplus(hi - softplus(hi - v) - lo)``). Decoder p(x | z, c): z is mapped to the bottleneck by the authors'
``MLP(latent -> bottleneck, hidden = mid channels, n_layers = 1)`` (two hidden ReLU layers), then one mid block and
the U-Net up path *without* skip connections (there is no x at sampling time), FiLM-conditioned on the context.

Loss, per sample and averaged over the batch, in normalized space: the reconstruction error as the authors define
it, the (unsquared) Frobenius norm ``||x_rec - x||`` over control points and joints, plus beta KL (beta = 0.1, the
authors' training default). The reparametrization uses ``std = exp(logvar / 2)``: the authors' code draws with
``0.5 exp(logvar)``, which disagrees with the Gaussian its KL term assumes (a slip, not a modelling choice), so it is
not copied (README, "Paper vs the authors' configs"). The bottleneck length depends on H, so a CVAE is built for one
horizon.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn
from torch.nn import functional as F

from mpd.models.context import ContextEncoder, mlp
from mpd.models.diffusion import randn
from mpd.models.unet import (
    Conv1dBlock,
    ResidualTemporalBlock,
    down_path,
    level_channels,
    pad_horizon,
    padded_horizon,
    up_path,
)
from mpd.tasks.spec import ModelSpec

LATENT_DIM = 32
BETA = 0.1
LOGVAR_MIN, LOGVAR_MAX = -7.0, 2.0


def soft_clip(v: torch.Tensor, lo: float = LOGVAR_MIN, hi: float = LOGVAR_MAX) -> torch.Tensor:
    """Differentiable clamp of v to about [lo, hi] (the top is hi + softplus(lo - hi) above): ``lo + softplus(hi -
    softplus(hi - v) - lo)``."""
    return lo + F.softplus(hi - F.softplus(hi - v) - lo)


def kl_standard_normal(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(N(mu, diag(exp(logvar))) || N(0, I)) per sample: ``0.5 sum(mu^2 + exp(logvar) - 1 - logvar)``."""
    return 0.5 * (mu.square() + logvar.exp() - 1 - logvar).sum(dim=-1)


class CVAE(nn.Module):
    def __init__(
        self,
        dof: int,
        horizon: int,
        context_kind: str,
        spec: ModelSpec,
        latent_dim: int = LATENT_DIM,
        beta: float = BETA,
    ):
        super().__init__()
        self.dof = dof
        self.horizon = horizon
        self.context_kind = context_kind
        self.latent_dim = latent_dim
        self.beta = beta
        levels = level_channels(dof, spec.unet_dim, spec.unet_dim_mults)
        self.n_levels = len(levels)
        cond_dim = spec.context_dim
        self.context_encoder = ContextEncoder(context_kind, dof, spec.context_dim, spec.context_layers)
        mid = levels[-1][1]
        self.bottleneck = (mid, padded_horizon(horizon, self.n_levels) // 2 ** (self.n_levels - 1))
        flat = mid * self.bottleneck[1]
        # encoder
        self.downs = down_path(levels, cond_dim)
        self.mid1 = ResidualTemporalBlock(mid, mid, cond_dim)
        self.to_latent = nn.Linear(flat, 2 * latent_dim)
        # decoder
        self.from_latent = mlp(latent_dim, flat, n_layers=1, hidden_dim=mid)
        self.mid2 = ResidualTemporalBlock(mid, mid, cond_dim)
        self.ups = up_path(levels, cond_dim, skips=False)
        top = levels[0][1]
        self.final = nn.Sequential(Conv1dBlock(top, top), nn.Conv1d(top, dof, 1))

    def encode(self, x: torch.Tensor, context_emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mu, logvar), each ``(B, latent_dim)``; logvar soft-clipped to (LOGVAR_MIN, LOGVAR_MAX)."""
        if tuple(x.shape[1:]) != (self.horizon, self.dof):
            raise ValueError(f"CVAE built for x of shape (B, {self.horizon}, {self.dof}), got {tuple(x.shape)}")
        h = pad_horizon(x.transpose(1, 2), self.n_levels)
        for res1, res2, down in self.downs:
            h = down(res2(res1(h, context_emb), context_emb))
        h = self.mid1(h, context_emb)
        mu, logvar = self.to_latent(h.flatten(1)).chunk(2, dim=-1)
        return mu, soft_clip(logvar)

    def decode(self, z: torch.Tensor, context_emb: torch.Tensor) -> torch.Tensor:
        h = self.mid2(self.from_latent(z).reshape(z.shape[0], *self.bottleneck), context_emb)
        for res1, res2, up in self.ups:
            h = up(res2(res1(h, context_emb), context_emb))
        return self.final(h)[..., : self.horizon].transpose(1, 2)

    def _embed(self, context: Mapping[str, torch.Tensor], batch: int) -> torch.Tensor:
        emb = self.context_encoder(context)
        return emb.expand(batch, -1) if emb.shape[0] == 1 and batch > 1 else emb

    def forward(
        self, x: torch.Tensor, context: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(reconstruction, mu, logvar), with z drawn by the reparametrization trick."""
        emb = self._embed(context, x.shape[0])
        mu, logvar = self.encode(x, emb)
        z = mu + (0.5 * logvar).exp() * randn(tuple(mu.shape), generator, mu.device, mu.dtype)
        return self.decode(z, emb), mu, logvar

    def loss_terms(
        self,
        x0: torch.Tensor,
        context: Mapping[str, torch.Tensor],
        generator: torch.Generator | None = None,
        kl_scale: float = 1.0,
    ) -> dict[str, torch.Tensor]:
        """``kl_scale`` multiplies beta (a KL warm-up: ``training.kl_warmup_steps``)."""
        recon, mu, logvar = self(x0, context, generator)
        rec = torch.linalg.vector_norm((recon - x0).flatten(1), dim=-1).mean()
        kl = kl_standard_normal(mu, logvar).mean()
        return {"loss": rec + kl_scale * self.beta * kl, "reconstruction": rec, "kl": kl}

    def loss(
        self,
        x0: torch.Tensor,
        context: Mapping[str, torch.Tensor],
        generator: torch.Generator | None = None,
        kl_scale: float = 1.0,
    ) -> torch.Tensor:
        return self.loss_terms(x0, context, generator, kl_scale)["loss"]

    @torch.no_grad()
    def sample(
        self, context: Mapping[str, torch.Tensor], n: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """``(n, H, d)`` decoded from z ~ N(0, I) (normalized space); context of batch 1 or n."""
        device = next(self.parameters()).device
        z = randn((n, self.latent_dim), generator, device)
        return self.decode(z, self._embed(context, n))
