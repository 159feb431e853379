"""Where a prior's loss sits: the validation epsilon-MSE split by diffusion step (five bands of t) and by row (the
first free rows, the middle, the final row), for a checkpoint's raw and EMA weights, in fp32 and under bf16
autocast (the cpu profile trains under it), on 2048 validation samples with 4 seeds of t and noise.

    MPD_CACHE=... python reports/recipe-study-panda/loss_split.py TASK DATASET <model.pt or last.pt> ...

Made to find why some `recipe-study-panda-goal` trainings stalled at a constant loss (0.19-0.33) where the plain
recipe went on to 0.05: a stall confined to some steps or rows, or to bf16, shows here.
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from mpd.data.dataset import load_dataset
from mpd.models.checkpoint import build_network, read_checkpoint
from mpd.models.data import SPLIT_VAL, training_arrays
from mpd.models.diffusion import q_sample, randint, randn
from mpd.models.normalizer import Normalizer
from mpd.models.train import _to_device
from mpd.schema import from_dict
from mpd.tasks import load_task
from mpd.tasks.spec import ModelSpec

BANDS = ((0, 5), (5, 20), (20, 50), (50, 80), (80, 100))


def split(net, x: torch.Tensor, ctx: dict, bf16: bool, seeds: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample, per-row squared error [seeds * N, rows] and the draws' steps [seeds * N]."""
    errs, ts = [], []
    for rep in range(seeds):
        g = torch.Generator().manual_seed(rep)
        t = randint(net.n_diffusion_steps, (len(x),), g, x.device)
        noise = randn(tuple(x.shape), g, x.device, x.dtype)
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            pred = net(q_sample(x, t, noise, net.schedule), t, ctx)
        errs.append((pred.float() - noise).pow(2).mean(2).numpy())
        ts.append(t.numpy())
    return np.concatenate(errs), np.concatenate(ts)


def main(task_name: str, dataset: str, paths: list[str]) -> None:
    torch.set_num_threads(1)
    task, ds = load_task(task_name), load_dataset(dataset)
    arr = training_arrays(task, ds, "bspline")
    val = np.flatnonzero(arr.split == SPLIT_VAL)[:2048]
    head = " | ".join(f"t {a}-{b - 1}" for a, b in BANDS)
    print(f"| model | weights | precision | all | {head} | rows 0-2 | middle rows | final row |")
    print("| --- | --- | --- |" + " ---: |" * (len(BANDS) + 4))
    for path in paths:
        ck = read_checkpoint(path)
        spec = from_dict(ModelSpec, ck["model_spec"], source=path, where="model_spec")
        net = build_network(ck["kind"], int(ck["dof"]), int(ck["horizon"]), ck["context_kind"], spec).eval()
        x_norm = Normalizer.from_dict(ck["normalizers"]["x"])
        ctx_norms = {k: Normalizer.from_dict(v) for k, v in ck["normalizers"]["context"].items()}
        data = _to_device(arr, val, x_norm, ctx_norms, torch.device("cpu"))
        for key in ("weights", "ema_weights"):
            net.load_state_dict(ck[key])
            for bf16 in (False, True):
                err, t = split(net, data.x, data.context, bf16)
                bands = " | ".join(f"{err[(t >= a) & (t < b)].mean():.3f}" for a, b in BANDS)
                print(
                    f"| {ck['identity'][:8]} step {ck.get('step', '?')} | {key} | {'bf16' if bf16 else 'fp32'}"
                    f" | {err.mean():.4f} | {bands} | {err[:, :3].mean():.3f} | {err[:, 3:-1].mean():.3f}"
                    f" | {err[:, -1].mean():.3f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
