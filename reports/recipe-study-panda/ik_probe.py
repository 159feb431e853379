"""How fast can a network learn the goal configuration alone? A probe for the Panda prior's slow goal learning.

The Panda prior has to produce a final configuration whose end-effector pose is the context's goal pose: a learned
inverse kinematics (a 1-D self-motion manifold of solutions per pose, in several branches). This probe trains the
smallest model of that part alone: a conditional diffusion model (same cosine schedule, epsilon loss, 100 steps) of
the final configuration w_last only (the last free B-spline row, 7 values), given the same normalized context
(q_start, goal position, flattened goal rotation), with an MLP denoiser, and measures how far its samples end from
the goal pose on held-out (validation) contexts, after each budget of steps. If this small model learns the map
quickly, the U-Net prior is slow for its own reasons (its size, its conditioning path, its loss spread over 32
rows); if it is slow too, the map itself is what takes the training.

Usage: MPD_CACHE=... python ik_probe.py [TASK] [DATASET] [STEPS,STEPS,...] [WIDTH] [film|encoder|encoder-he]
(defaults: EnvSpheres3D-RobotPanda EnvSpheres3D-RobotPanda-cpu 1000,3000,10000,30000 256; ``film``: the context enters
only through FiLM of the hidden layers, as in the U-Net, instead of being concatenated to the input; ``encoder``: the
context is first embedded by the priors' own context MLPs (mpd.models.context.ContextEncoder, the Panda's sizes:
128 wide, 2 layers, trained with the probe), ``encoder-he`` the same with ModelSpec.context_init = "he")
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np
import torch
from torch import nn

from mpd.data.dataset import load_dataset
from mpd.models.context import ContextEncoder
from mpd.models.data import SPLIT_TRAIN, SPLIT_VAL, fit_normalizers, training_arrays
from mpd.models.diffusion import ddpm_step, get_schedule, q_sample
from mpd.models.unet import SinusoidalPosEmb
from mpd.robots.ik import pose_errors
from mpd.tasks import load_task

time_embedding = SinusoidalPosEmb(32)  # the U-Net's embedding of the diffusion step


class Denoiser(nn.Module):
    def __init__(self, dof: int, ctx_dim: int, width: int):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(dof + ctx_dim + 32, width),
            nn.Mish(),
            nn.Linear(width, width),
            nn.Mish(),
            nn.Linear(width, width),
            nn.Mish(),
            nn.Linear(width, dof),
        )

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, ctx: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([x_t, ctx, time_embedding(t)], dim=-1))


class FilmDenoiser(nn.Module):
    """The same MLP, but the context reaches it only as the U-Net's does: an embedding of [time, context] that
    scales and shifts each hidden layer (FiLM); the input is the noisy configuration alone."""

    def __init__(self, dof: int, ctx_dim: int, width: int):
        super().__init__()
        self.ctx = nn.Sequential(nn.Linear(ctx_dim, 128), nn.ReLU(), nn.Linear(128, 128), nn.ReLU())
        self.inp = nn.Linear(dof, width)
        self.hidden = nn.ModuleList([nn.Linear(width, width) for _ in range(2)])
        self.film = nn.ModuleList([nn.Sequential(nn.Mish(), nn.Linear(128 + 32, 2 * width)) for _ in range(3)])
        self.out = nn.Linear(width, dof)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, ctx: torch.Tensor) -> torch.Tensor:
        cond = torch.cat([self.ctx(ctx), time_embedding(t)], dim=-1)
        h = self.inp(x_t)
        for i, film in enumerate(self.film):
            scale, shift = film(cond).chunk(2, dim=-1)
            h = nn.functional.mish(h * (1 + scale) + shift)
            if i < len(self.hidden):
                h = self.hidden[i](h)
        return self.out(h)


class EncoderDenoiser(nn.Module):
    """The concatenating MLP, with the context embedded by the priors' ContextEncoder first (from the flat context:
    q_start, goal position, flattened goal rotation)."""

    def __init__(self, dof: int, ctx_dim: int, width: int, init: str):
        super().__init__()
        self.dof = dof
        self.encoder = ContextEncoder("goal_ee_pose", dof, 128, 2, init)
        self.denoiser = Denoiser(dof, 128, width)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, ctx: torch.Tensor) -> torch.Tensor:
        d = self.dof
        fields = {"q_start": ctx[:, :d], "ee_pos": ctx[:, d : d + 3], "ee_rot": ctx[:, d + 3 :].reshape(-1, 3, 3)}
        return self.denoiser(x_t, t, self.encoder(fields))


@torch.no_grad()
def sample(net: nn.Module, ctx: torch.Tensor, n_per: int, dof: int, seed: int) -> torch.Tensor:
    """DDPM, all 100 steps (the sampler is not what this probe measures)."""
    sch = get_schedule()
    g = torch.Generator().manual_seed(seed)
    c = ctx.repeat_interleave(n_per, dim=0)
    x = torch.randn(len(c), dof, generator=g)
    for t in reversed(range(sch.n_steps)):
        eps = net(x, torch.full((len(c),), t), c)
        x = ddpm_step(x, eps, t, torch.randn(x.shape, generator=g), schedule=sch)
    return x


def main(task_name: str, dataset: str, budgets: list[int], width: int, mode: str = "concat") -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    task, ds = load_task(task_name), load_dataset(dataset)
    arr = training_arrays(task, ds, "bspline")
    x_norm, ctx_norms = fit_normalizers(arr)
    w = torch.as_tensor(arr.x[:, -1, :])  # the final configuration (the last free row), raw units
    y = x_norm.normalize(w[:, None, :])[:, 0, :]
    ctx = torch.cat(
        [
            ctx_norms["q_start"].normalize(torch.as_tensor(arr.context["q_start"])),
            ctx_norms["ee_pos"].normalize(torch.as_tensor(arr.context["ee_pos"])),
            torch.as_tensor(arr.context["ee_rot"]).flatten(1),
        ],
        dim=-1,
    ).float()
    tr, va = np.flatnonzero(arr.split == SPLIT_TRAIN), np.flatnonzero(arr.split == SPLIT_VAL)[:200]
    y_tr, c_tr = y[tr].float(), ctx[tr]
    dof = y.shape[1]
    if mode in ("encoder", "encoder-he"):
        net = EncoderDenoiser(dof, ctx.shape[1], width, "he" if mode == "encoder-he" else "default")
    elif mode in ("film", "concat"):
        net = (FilmDenoiser if mode == "film" else Denoiser)(dof, ctx.shape[1], width)
    else:
        raise ValueError(f"unknown mode {mode!r} (concat, film, encoder, encoder-he)")
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    sch, g = get_schedule(), torch.Generator().manual_seed(1)
    goal_pos = torch.as_tensor(arr.context["ee_pos"][va]).double()
    goal_rot = torch.as_tensor(arr.context["ee_rot"][va]).double()
    n_per = 10
    print(
        f"{task_name}: {len(tr)} training rows, {len(va)} validation contexts x {n_per} samples, width {width}"
        f", context: {mode}"
    )
    print("| steps | train [s] | loss | EE position error, median [cm] | best of 10 [cm] | rotation, median [deg] |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: |")
    step, t0, ema_loss = 0, time.perf_counter(), float("nan")
    for budget in budgets:
        net.train()
        while step < budget:
            i = torch.randint(len(tr), (512,), generator=g)
            t = torch.randint(sch.n_steps, (512,), generator=g)
            noise = torch.randn(512, dof, generator=g)
            loss = (net(q_sample(y_tr[i], t, noise, sch), t, c_tr[i]) - noise).pow(2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            ema_loss = loss.item() if math.isnan(ema_loss) else 0.99 * ema_loss + 0.01 * loss.item()
            step += 1
        train_s = time.perf_counter() - t0
        net.eval()
        q = x_norm.unnormalize(sample(net, ctx[va], n_per, dof, seed=2)[:, None, :])[:, 0, :].double()
        ep, er = pose_errors(task.robot, q, goal_pos.repeat_interleave(n_per, 0), goal_rot.repeat_interleave(n_per, 0))
        ep, er = ep.reshape(-1, n_per), er.reshape(-1, n_per)
        print(
            f"| {step} | {train_s:.0f} | {ema_loss:.4f} | {100 * ep.median():.1f}"
            f" | {100 * ep.min(1).values.median():.1f} | {math.degrees(er.median()):.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    a = sys.argv[1:]
    main(
        a[0] if len(a) > 0 else "EnvSpheres3D-RobotPanda",
        a[1] if len(a) > 1 else "EnvSpheres3D-RobotPanda-cpu",
        [int(s) for s in (a[2] if len(a) > 2 else "1000,3000,10000,30000").split(",")],
        int(a[3]) if len(a) > 3 else 256,
        a[4] if len(a) > 4 else "concat",
    )
