"""Speed of the Panda-sized denoising network on CPU: one forward pass (batch 100, what a planner calls per
denoising step) and one training step (batch 512, the paper's Panda batch size).

Run: ``pytest benchmarks/test_bench_models.py -m benchmark --benchmark-enable -s`` (``nox -s benchmarks``).
"""

from __future__ import annotations

import pytest
import torch

from mpd.models import DiffusionModel
from mpd.models.train import make_optimizer
from mpd.tasks.spec import ModelSpec, TrainingSpec

pytestmark = pytest.mark.benchmark

# sizes of the Panda tasks (EnvSpheres3D / EnvWarehouse): 7 joints, (1, 2, 4, 8) U-Net, context dim 128
PANDA = ModelSpec(unet_dim=32, unet_dim_mults=[1, 2, 4, 8], context_dim=128, context_layers=2)
DOF = 7


@pytest.fixture(params=[1, 2], ids=lambda n: f"threads{n}")
def threads(request):
    old = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(old)


def panda_model(horizon: int) -> DiffusionModel:
    torch.manual_seed(0)
    return DiffusionModel(DOF, horizon, "goal_ee_pose", PANDA)


def panda_batch(batch: int, horizon: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    x = torch.rand(batch, horizon, DOF, generator=g) * 2 - 1
    rot = torch.linalg.qr(torch.randn(batch, 3, 3, generator=g)).Q
    ctx = {
        "q_start": torch.rand(batch, DOF, generator=g) * 2 - 1,
        "ee_pos": torch.rand(batch, 3, generator=g),
        "ee_rot": rot,
    }
    return x, ctx


@pytest.mark.parametrize("horizon", [24, 32])
def test_forward_batch100(benchmark, threads, horizon):
    model = panda_model(horizon).eval()
    x, ctx = panda_batch(100, horizon)
    n_params = sum(p.numel() for p in model.parameters())
    benchmark.extra_info.update(parameters=n_params, threads=threads, horizon=horizon, batch=100)
    print(f"\nPanda denoiser: {n_params:,} parameters (H={horizon}, d={DOF})")

    def forward():
        with torch.no_grad():
            return model(x, 50, ctx)

    out = benchmark.pedantic(forward, rounds=20, warmup_rounds=2)
    assert out.shape == x.shape


@pytest.mark.parametrize("horizon", [24, 32])
def test_training_step_batch512(benchmark, threads, horizon):
    model = panda_model(horizon).train()
    x, ctx = panda_batch(512, horizon)
    opt = make_optimizer(model, TrainingSpec(batch_size=512, steps=1))
    g = torch.Generator().manual_seed(0)

    def step():
        loss = model.loss(x, ctx, g)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        return loss

    loss = benchmark.pedantic(step, rounds=8, warmup_rounds=1)
    median = benchmark.stats.stats.median
    benchmark.extra_info.update(threads=threads, horizon=horizon, batch=512, steps_per_s=1 / median)
    print(f"\nPanda training step (batch 512, H={horizon}, {threads} threads): {1 / median:.2f} steps/s")
    assert torch.isfinite(loss)
