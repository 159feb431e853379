"""Does a trained prior's final configuration reach the goal pose, valid or not? For each model: 200 validation
contexts x 10 unguided samples (DDIM, 15 steps, the paper's sampler), the end-effector pose of each sample's last
free row (the final configuration) against the context's goal pose; and the validation loss split into the final
row and the other rows (2048 validation samples, 4 seeds of t and noise), so a model's goal learning is seen apart
from its validity (the results tables' EE errors are over valid samples only).

Usage: MPD_CACHE=... python goal_reach.py TASK DATASET MODEL_PT [MODEL_PT ...]
(MPD_GOAL_REACH_SAMPLER=ddpm: all 100 DDPM steps instead, the probe's sampler)
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np
import torch

from mpd.data.dataset import load_dataset
from mpd.models.checkpoint import load_model
from mpd.models.data import SPLIT_VAL, training_arrays
from mpd.models.diffusion import q_sample, randint, randn
from mpd.models.diffusion import sample as diffusion_sample
from mpd.models.train import _to_device
from mpd.robots.ik import pose_errors
from mpd.tasks import load_task


def row_losses(net, x: torch.Tensor, ctx: dict, seeds: int = 4) -> tuple[float, float]:
    """Validation epsilon-MSE of the final row and of the other rows (the plain loss's draws)."""
    last, rest = [], []
    for rep in range(seeds):
        g = torch.Generator().manual_seed(rep)
        t = randint(net.n_diffusion_steps, (len(x),), g, x.device)
        noise = randn(tuple(x.shape), g, x.device, x.dtype)
        with torch.no_grad():
            sq = (net(q_sample(x, t, noise, net.schedule), t, ctx) - noise).pow(2).mean((0, 2))
        last.append(float(sq[-1]))
        rest.append(float(sq[:-1].mean()))
    return float(np.mean(last)), float(np.mean(rest))


def main(task_name: str, dataset: str, model_paths: list[str]) -> None:
    torch.set_num_threads(1)
    task, ds = load_task(task_name), load_dataset(dataset)
    arr = training_arrays(task, ds, "bspline")
    val = np.flatnonzero(arr.split == SPLIT_VAL)
    n_ctx, n_per = 200, 10
    goal_pos = torch.as_tensor(arr.context["ee_pos"][val[:n_ctx]]).double().repeat_interleave(n_per, 0)
    goal_rot = torch.as_tensor(arr.context["ee_rot"][val[:n_ctx]]).double().repeat_interleave(n_per, 0)
    sampler = os.environ.get("MPD_GOAL_REACH_SAMPLER", "ddim")
    print(f"{task_name}: {n_ctx} validation contexts x {n_per} unguided samples ({sampler}); loss on 2048 samples")
    print(
        "| model | steps | goal_row_weight | EE position error, median [cm] | best of 10 [cm] | rotation, median [deg]"
        " | val loss, final row | val loss, other rows |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for path in model_paths:
        m = load_model(path)
        net = m.network.eval()
        data = _to_device(arr, val[:2048], m.x_normalizer, m.context_normalizers, torch.device("cpu"))
        ctx = {k: v[:n_ctx].repeat_interleave(n_per, 0) for k, v in data.context.items()}
        x = diffusion_sample(net, ctx, n_ctx * n_per, sampler=sampler, generator=torch.Generator().manual_seed(2))
        q = m.x_normalizer.unnormalize(x)[:, -1, :].double()
        ep, er = pose_errors(task.robot, q, goal_pos, goal_rot)
        ep, er = ep.reshape(-1, n_per), er.reshape(-1, n_per)
        last, rest = row_losses(net, data.x, data.context)
        ts = m.meta["training_spec"]
        print(
            f"| {m.meta['identity'][:8]} | {ts['steps']} | {ts.get('goal_row_weight', 1.0):g} | {100 * ep.median():.1f}"
            f" | {100 * ep.min(1).values.median():.1f} | {math.degrees(er.median()):.1f} | {last:.4f} | {rest:.4f} |",
            flush=True,
        )


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
