"""Speed of the Panda-sized denoising network on CPU: one forward pass (batch 100, what a planner calls per
denoising step) and one training step (batch 512, the paper's Panda batch size).

Run: ``pytest benchmarks/test_bench_models.py -m benchmark --benchmark-enable -s`` (``nox -s benchmarks``).
"""

from __future__ import annotations

import pytest
import torch
from cpu_peak import peak_gflops

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


@pytest.mark.parametrize("layout", ["channels-last-2d", "conv1d"])
@pytest.mark.parametrize("horizon", [24, 32])
def test_forward_batch100(benchmark, threads, horizon, layout):
    """``layout``: the U-Net's CPU inference path (its convolutions as channels-last 2-D ones, the default) or its 1-D
    reference (``TemporalUnet.channels_last_2d = False``)."""
    model = panda_model(horizon).eval()
    model.unet.channels_last_2d = layout == "channels-last-2d"
    x, ctx = panda_batch(100, horizon)
    n_params = sum(p.numel() for p in model.parameters())
    benchmark.extra_info.update(parameters=n_params, threads=threads, horizon=horizon, batch=100, layout=layout)
    print(f"\nPanda denoiser: {n_params:,} parameters (H={horizon}, d={DOF})")

    def forward():
        with torch.no_grad():
            return model(x, 50, ctx)

    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as fc:
        forward()
    flops = fc.get_total_flops()
    out = benchmark.pedantic(forward, rounds=20, warmup_rounds=2)
    median = benchmark.stats.stats.median
    peak = peak_gflops(threads)
    achieved = flops / 1e9 / median
    benchmark.extra_info.update(
        gflop_per_forward=flops / 1e9, gflop_per_s=achieved, peak_fp32_gflop_per_s=peak["fp32"],
        fraction_of_fp32_peak=achieved / peak["fp32"],
    )  # fmt: skip
    print(
        f"forward: {flops / 1e9:.2f} GFLOP, {achieved:.0f} GFLOP/s = {100 * achieved / peak['fp32']:.0f} % of the "
        f"nominal fp32 peak of {threads} cores ({peak['fp32']:.0f} GFLOP/s at {peak['ghz']:.2f} GHz)"
    )
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


# --- training throughput by precision: the 2-D networks (batch 128) and the Panda ones (batch 512) ------------------
POINT_MASS = ModelSpec()  # the paper's 2-D sizes: (1, 2, 4) U-Net, dim 32, context dim 32
CASES = {
    # name: (spec, dof, horizon of free control points, context kind, batch)
    "2d": (POINT_MASS, 2, 16, "goal_joint_position", 128),
    # larger batches compute more samples per second on a CPU (the recipe study's batch axis)
    "2d-b512": (POINT_MASS, 2, 16, "goal_joint_position", 512),
    "panda": (PANDA, DOF, 24, "goal_ee_pose", 512),
}


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("case", list(CASES))
def test_training_steps_per_s_by_precision(benchmark, threads, case, precision):
    """One training step as `train_model` runs it (forward under the profile's autocast, backward, grad clip, fused
    AdamW): the steps/s of fp32 and bf16 side by side in one run, with the achieved GFLOP/s of each."""
    from torch.utils.flop_counter import FlopCounterMode

    spec, dof, horizon, kind, batch = CASES[case]
    torch.manual_seed(0)
    model = DiffusionModel(dof, horizon, kind, spec).train()
    if kind == "goal_ee_pose":
        x, ctx = panda_batch(batch, horizon)
    else:
        g0 = torch.Generator().manual_seed(0)
        x = torch.rand(batch, horizon, dof, generator=g0) * 2 - 1
        ctx = {"q_start": torch.rand(batch, dof, generator=g0), "q_goal": torch.rand(batch, dof, generator=g0)}
    opt = make_optimizer(model, TrainingSpec(batch_size=batch, steps=1))
    g = torch.Generator().manual_seed(0)
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16")

    def step():
        with autocast:
            loss = model.loss(x, ctx, g)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        return loss

    with FlopCounterMode(display=False) as fc:
        step()
    flops = fc.get_total_flops()
    loss = benchmark.pedantic(step, rounds=8 if case.startswith("2d") else 4, warmup_rounds=1)
    median = benchmark.stats.stats.median
    peak = peak_gflops(threads)[precision]
    benchmark.extra_info.update(
        case=case, precision=precision, threads=threads, batch=batch, horizon=horizon, steps_per_s=1 / median,
        samples_per_s=batch / median,
        gflop_per_step=flops / 1e9, gflop_per_s=flops / 1e9 / median, peak_gflop_per_s=peak,
        fraction_of_peak=flops / 1e9 / median / peak,
    )  # fmt: skip
    print(
        f"\n{case} training step, {precision}, {threads} threads: {1 / median:.2f} steps/s "
        f"({batch / median:.0f} samples/s), {flops / 1e9 / median:.0f} GFLOP/s "
        f"({100 * flops / 1e9 / median / peak:.0f} % of the nominal {precision} peak)"
    )
    assert torch.isfinite(loss)
