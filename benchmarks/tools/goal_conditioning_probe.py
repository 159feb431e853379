"""Does the Panda prior use its goal pose at all? Train the EnvSpheres3D diffusion B-spline prior (the task's ``cpu``
recipe) on the first K training paths of EnvSpheres3D-RobotPanda-cpu until it memorises them, then measure

(a) the end-effector position error of sampled final configurations on 20 of those training contexts, beside the
    data's own (0) and that of a random pairing of final configurations and goals (a prior that ignores the goal);
(b) the denoising loss on the final control point (the goal configuration) with the true context and with the
    contexts shuffled, at several noise levels: equal losses would mean the network ignores the context.

    MPD_CACHE=... OMP_NUM_THREADS=1 python benchmarks/tools/goal_conditioning_probe.py K STEPS BATCH TAG

(2026-12-02: K=256, 1500 steps, batch 128: 413 s on one core; see the closing note of the Panda issue.) The model
goes to ``$PROBE_CACHE`` (default ``/tmp/goal-probe-TAG``, a scratch cache; the dataset comes from ``$MPD_CACHE``).
"""

import dataclasses
import json
import os
import sys
import time

import numpy as np
import torch

from mpd.data.dataset import load_dataset
from mpd.models import get_schedule, load_model, q_sample
from mpd.models.data import TrainingArrays, training_arrays
from mpd.models.train import train_model
from mpd.tasks import load_task

torch.set_num_threads(1)

K = int(sys.argv[1])
steps = int(sys.argv[2])
bs = int(sys.argv[3])
tag = sys.argv[4]
task = load_task("EnvSpheres3D-RobotPanda")
ds = load_dataset("EnvSpheres3D-RobotPanda-cpu")
arr = training_arrays(task, ds, "bspline")
idx = np.flatnonzero(arr.split == 0)[:K]
sub = TrainingArrays(
    x=arr.x[idx],
    context={k: v[idx] for k, v in arr.context.items()},
    split=np.zeros(len(idx), np.int8),
    task_name=arr.task_name,
    task_hash=arr.task_hash,
    dataset_hash=arr.dataset_hash + f"-sub{K}",
    parametrization=arr.parametrization,
    parametrization_settings=arr.parametrization_settings,
)
ts = dataclasses.replace(
    task.training("cpu"),
    steps=steps,
    batch_size=bs,
    val_every=steps,
    checkpoint_every=steps,
    ema_start=min(500, steps // 4),
)
t0 = time.time()
path = train_model(
    sub,
    "diffusion",
    task.spec.model,
    ts,
    seed=0,
    cache=os.environ.get("PROBE_CACHE", f"/tmp/goal-probe-{tag}"),
    shipped=False,
    progress=False,
)
print("train s", round(time.time() - t0, 1), flush=True)
prior = load_model(path)
net = prior.network.eval()
robot = task.robot
# (a) sample 10 per context on 20 training contexts, EE error of the final configuration
errs, errs_data = [], []
g = torch.Generator().manual_seed(0)
for i in range(20):
    ctx = {k: v[i] for k, v in sub.context.items()}
    with torch.no_grad():
        x = prior.sample(ctx, 10, generator=g)
    p, _ = robot.ee_pose(x[:, -1].double())
    errs.append((p - torch.as_tensor(ctx["ee_pos"]).double()).norm(dim=-1).mean().item())
    p2, _ = robot.ee_pose(torch.as_tensor(sub.x[i, -1]).double()[None])
    errs_data.append((p2[0] - torch.as_tensor(ctx["ee_pos"]).double()).norm().item())
# random pairing: EE error if the final configuration came from another context
pr, _ = robot.ee_pose(torch.as_tensor(sub.x[:200, -1]).double())
rand = (pr - torch.as_tensor(sub.context["ee_pos"][np.roll(np.arange(200), 1)]).double()).norm(dim=-1).mean().item()
# (b) loss on the final row, true vs shuffled context, several noise levels
xn = prior.x_normalizer.normalize(torch.as_tensor(sub.x[:256]))
ctx = prior.normalize_context({k: v[:256] for k, v in sub.context.items()})
perm = torch.roll(torch.arange(xn.shape[0]), 1)
ctx_s = {k: v[perm] for k, v in ctx.items()}
out = {}
for t in (5, 20, 50, 80):
    noise = torch.randn(xn.shape, generator=torch.Generator().manual_seed(t))
    xt = q_sample(xn, torch.full((xn.shape[0],), t), noise, get_schedule())
    with torch.no_grad():
        e1 = net(xt, t, ctx)
        e2 = net(xt, t, ctx_s)
    out[t] = (
        round(((e1 - noise)[:, -1] ** 2).mean().item(), 4),
        round(((e2 - noise)[:, -1] ** 2).mean().item(), 4),
        round(((e1 - noise)[:, :-1] ** 2).mean().item(), 4),
    )
print(
    json.dumps(
        {
            "K": K,
            "steps": steps,
            "ee_err_samples_m": round(float(np.mean(errs)), 3),
            "ee_err_data_m": round(float(np.mean(errs_data)), 4),
            "ee_err_random_pairing_m": round(rand, 3),
            "last_row_loss_true_vs_shuffled_vs_otherrows": out,
        }
    ),
    flush=True,
)
