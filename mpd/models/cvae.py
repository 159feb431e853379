"""Conditional VAE baseline (paper, "Baselines") on the temporal U-Net backbone.

Encoder q(z | x, c): the U-Net down path and mid blocks on x, FiLM-conditioned on the context embedding; the
flattened bottleneck is projected to the mean and log-variance of a 32-D Gaussian. Decoder p(x | z, c): z is
projected back to the bottleneck shape and run through the U-Net up path *without* skip connections (there is
no x at sampling time), FiLM-conditioned on the context. Loss = sum of squared reconstruction errors + beta
KL (beta = 0.1), both per sample and averaged over the batch, in normalized space. The bottleneck length
depends on H, so a CVAE is built for one horizon.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from mpd.models.context import ContextEncoder
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
        self.mid2 = ResidualTemporalBlock(mid, mid, cond_dim)
        self.to_latent = nn.Linear(flat, 2 * latent_dim)
        # decoder
        self.from_latent = nn.Linear(latent_dim, flat)
        self.ups = up_path(levels, cond_dim, skips=False)
        top = levels[0][1]
        self.final = nn.Sequential(Conv1dBlock(top, top), nn.Conv1d(top, dof, 1))

    def encode(self, x: torch.Tensor, context_emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mu, logvar), each ``(B, latent_dim)``."""
        if tuple(x.shape[1:]) != (self.horizon, self.dof):
            raise ValueError(
                f"CVAE built for x of shape (B, {self.horizon}, {self.dof}), got {tuple(x.shape)}"
            )
        h = pad_horizon(x.transpose(1, 2), self.n_levels)
        for res1, res2, down in self.downs:
            h = down(res2(res1(h, context_emb), context_emb))
        h = self.mid2(self.mid1(h, context_emb), context_emb)
        mu, logvar = self.to_latent(h.flatten(1)).chunk(2, dim=-1)
        return mu, logvar

    def decode(self, z: torch.Tensor, context_emb: torch.Tensor) -> torch.Tensor:
        h = self.from_latent(z).reshape(z.shape[0], *self.bottleneck)
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
        self, x0: torch.Tensor, context: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> dict[str, torch.Tensor]:
        recon, mu, logvar = self(x0, context, generator)
        rec = (recon - x0).square().flatten(1).sum(dim=-1).mean()
        kl = kl_standard_normal(mu, logvar).mean()
        return {"loss": rec + self.beta * kl, "reconstruction": rec, "kl": kl}

    def loss(
        self, x0: torch.Tensor, context: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> torch.Tensor:
        return self.loss_terms(x0, context, generator)["loss"]

    @torch.no_grad()
    def sample(
        self, context: Mapping[str, torch.Tensor], n: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """``(n, H, d)`` decoded from z ~ N(0, I) (normalized space); context of batch 1 or n."""
        device = next(self.parameters()).device
        z = randn((n, self.latent_dim), generator, device)
        return self.decode(z, self._embed(context, n))
