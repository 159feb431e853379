"""How much does a trained prior use its context? Validation loss (2048 validation samples, 4 seeds of t and noise)
with the true context, with the goal fields (end-effector pose, or joint goal) of another sample, with the start of
another sample, and with the whole context of another sample.

Usage: MPD_CACHE=... python context_use.py TASK DATASET MODEL_PT  (the dataset must be generated in the cache)
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from mpd.data.dataset import load_dataset
from mpd.models.checkpoint import load_model
from mpd.models.data import SPLIT_VAL, training_arrays
from mpd.models.train import _to_device
from mpd.tasks import load_task


def main(task_name: str, dataset: str, model_path: str) -> None:
    torch.set_num_threads(1)
    task, ds, m = load_task(task_name), load_dataset(dataset), load_model(model_path)
    arr = training_arrays(task, ds, "bspline")
    idx = np.flatnonzero(arr.split == SPLIT_VAL)[:2048]
    # normalized as in training (the model's own normalizers)
    data = _to_device(arr, idx, m.x_normalizer, m.context_normalizers, torch.device("cpu"))
    x, ctx = data.x, data.context
    perm = torch.as_tensor(np.random.default_rng(0).permutation(len(idx)))
    goal_keys = [k for k in ctx if k != "q_start"]
    variants = {
        "true": ctx,
        "goal from another sample": {**ctx, **{k: ctx[k][perm] for k in goal_keys}},
        "start from another sample": {**ctx, "q_start": ctx["q_start"][perm]},
        "all from another sample": {k: v[perm] for k, v in ctx.items()},
    }
    net = m.network.eval()
    for name, c in variants.items():
        losses = []
        for rep in range(4):
            with torch.no_grad():
                losses.append(float(net.loss(x, c, torch.Generator().manual_seed(rep))))
        print(f"{name:28s} val loss {np.mean(losses):.4f}")


if __name__ == "__main__":
    main(*sys.argv[1:4])
