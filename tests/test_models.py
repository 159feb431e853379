"""mpd.models: normalizer, U-Net shapes, diffusion maths and samplers, CVAE, training, checkpoints."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import signal

import numpy as np
import pytest
import scipy.stats
import torch

import mpd.models.step as step_module
import mpd.models.train as train_module
from mpd.models import (
    CVAE,
    DiffusionModel,
    Normalizer,
    TrainingArrays,
    build_network,
    ddim_step,
    ddim_timesteps,
    ddpm_step,
    get_schedule,
    kl_standard_normal,
    list_models,
    load_model,
    model_identity,
    predict_x0,
    q_sample,
    read_checkpoint,
    sample,
    train_model,
)
from mpd.models.diffusion import ddpm_mean
from mpd.schema import ConfigError
from mpd.tasks import list_tasks, load_task
from mpd.tasks.spec import ModelSpec, TrainingSpec

TINY = ModelSpec(unet_dim=16, unet_dim_mults=[1, 2], context_dim=16)


pytestmark = pytest.mark.usefixtures("one_thread")


def toy_arrays(n: int = 16, horizon: int = 8, dof: int = 2, ee: bool = False, n_val: int = 0, seed: int = 0, **kw):
    """Bimodal arcs between random start and goal (the sign of the bend is the mode)."""
    rng = np.random.default_rng(seed)
    qs, qg = rng.uniform(-1, 1, (n, dof)), rng.uniform(-1, 1, (n, dof))
    s = np.linspace(0, 1, horizon + 2)[1:-1][None, :, None]
    bend = 0.3 * np.sin(np.pi * s) * rng.choice([-1.0, 1.0], (n, 1, 1))
    x = (qs[:, None] * (1 - s) + qg[:, None] * s + bend).astype(np.float32)
    if ee:
        rot = scipy.stats.special_ortho_group.rvs(3, size=n, random_state=seed)
        context = {"q_start": qs, "ee_pos": rng.uniform(-0.5, 0.5, (n, 3)), "ee_rot": rot}
    else:
        context = {"q_start": qs, "q_goal": qg}
    split = np.zeros(n, np.int8)
    split[n - n_val :] = 1
    fields = dict(task_name="Toy", task_hash="task0", dataset_hash="data0", parametrization="bspline")
    fields.update(kw)
    return TrainingArrays(x, context, split, **fields)


def tiny_training(**kw) -> TrainingSpec:
    base = dict(batch_size=32, steps=40, lr=1e-3, ema_start=20, ema_every=5, val_every=10, checkpoint_every=10)
    base.update(kw)
    return TrainingSpec(**base)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    arrays = toy_arrays(n_val=4)
    path = train_model(arrays, "diffusion", TINY, tiny_training(), seed=0, progress=False, cache=cache)
    return arrays, path, cache


# --- normalizer ------------------------------------------------------------------------------------------
def test_normalizer_maps_train_range_to_unit_box_and_back():
    x = torch.tensor(np.random.default_rng(0).normal(size=(50, 7, 3)) * [1.0, 10.0, 0.1], dtype=torch.float64)
    n = Normalizer.fit(x)
    z = n.normalize(x)
    assert torch.allclose(z.flatten(0, 1).min(0).values, -torch.ones(3, dtype=torch.float64))
    assert torch.allclose(z.flatten(0, 1).max(0).values, torch.ones(3, dtype=torch.float64))
    assert torch.allclose(n.unnormalize(z), x)
    assert Normalizer.from_dict(json.loads(json.dumps(n.to_dict()))) == n


def test_normalizer_guards_zero_range():
    n = Normalizer.fit(np.array([[1.0, 2.0], [1.0, 3.0]]))
    z = n.normalize(torch.tensor([[1.0, 2.5]]))
    assert torch.isfinite(z).all() and z[0, 0] == 0 and z[0, 1] == 0


def test_normalizer_gradient_scale_matches_autograd():
    n = Normalizer(lo=[-2.0, 0.0, 5.0], hi=[2.0, 0.5, 9.0])
    w = torch.tensor([1.0, -3.0, 0.5], dtype=torch.float64)
    z = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)

    def cost(raw):
        return (w * raw**2).sum()

    (g_norm,) = torch.autograd.grad(cost(n.unnormalize(z, clip=False)), z)
    raw = n.unnormalize(z, clip=False).detach().requires_grad_(True)
    (g_raw,) = torch.autograd.grad(cost(raw), raw)
    assert torch.allclose(n.grad_to_normalized(g_raw), g_norm)
    assert torch.allclose(n.grad_to_raw(g_norm), g_raw)


# --- networks --------------------------------------------------------------------------------------------
def task_horizons(task) -> list[int]:
    """B-spline free rows, waypoint free rows (n - 2, n - 1), plus sizes no power of 2 divides."""
    ncp = task.spec.trajectory.n_control_points
    return sorted({ncp - (5 if task.ee_goal else 6), ncp - 2, ncp - 1, 13, 1})


@pytest.mark.parametrize("task_name", list_tasks())
def test_unet_and_cvae_shapes_for_every_task(task_name):
    task = load_task(task_name)
    kind = task.spec.context.kind
    dof = task.dof
    for horizon in task_horizons(task):
        ctx = (
            {"q_start": torch.randn(2, dof), "ee_pos": torch.randn(2, 3), "ee_rot": torch.randn(2, 3, 3)}
            if task.ee_goal
            else {"q_start": torch.randn(2, dof), "q_goal": torch.randn(2, dof)}
        )
        x = torch.randn(2, horizon, dof)
        net = DiffusionModel(dof, horizon, kind, task.spec.model)
        assert net(x, torch.tensor([0, 99]), ctx).shape == (2, horizon, dof)
        assert net(x, 5, {k: v[:1] for k, v in ctx.items()}).shape == (2, horizon, dof)  # one shared context
        cvae = CVAE(dof, horizon, kind, task.spec.model)
        recon, mu, logvar = cvae(x, ctx)
        assert recon.shape == x.shape and mu.shape == logvar.shape == (2, 32)


def test_panda_network_size():
    spec = load_task("EnvSpheres3D-RobotPanda").spec.model
    n = sum(p.numel() for p in DiffusionModel(7, 32, "goal_ee_pose", spec).parameters())
    assert 3e6 < n < 6e6


def test_context_encoder_rejects_missing_or_misshaped_fields():
    net = DiffusionModel(2, 8, "goal_joint_position", TINY)
    with pytest.raises(ValueError, match="q_goal"):
        net(torch.randn(1, 8, 2), 0, {"q_start": torch.randn(1, 2)})
    with pytest.raises(ValueError, match="shape"):
        net(torch.randn(1, 8, 2), 0, {"q_start": torch.randn(1, 3), "q_goal": torch.randn(1, 2)})


# --- diffusion maths -------------------------------------------------------------------------------------
def test_cosine_schedule_and_closed_forms():
    sch = get_schedule()
    betas, abar = sch.tables["betas"], sch.tables["alphas_cumprod"]
    assert len(betas) == 100 and (betas >= 0).all() and betas.max() <= 0.999
    assert np.allclose(abar, np.cumprod(1 - betas)) and (np.diff(abar) < 0).all()
    x0, eps = torch.rand(5, 4, 2, dtype=torch.float64) * 2 - 1, torch.randn(5, 4, 2, dtype=torch.float64)
    t = torch.tensor([0, 3, 50, 98, 99])
    xt = q_sample(x0, t, eps)
    assert torch.allclose(predict_x0(xt, eps, t, clip=False), x0)
    # posterior mean via x0 == the paper's eq. (1/sqrt(alpha_t)) (x_t - beta_t / sqrt(1 - abar_t) eps)
    for step in (1, 10, 60, 99):
        paper = (xt - betas[step] / math.sqrt(1 - abar[step]) * eps) / math.sqrt(1 - betas[step])
        assert torch.allclose(ddpm_mean(xt, eps, step, clip=False), paper)


def test_ddpm_and_ddim_steps_end_at_clipped_x0():
    xt, eps = torch.randn(3, 4, 2) * 3, torch.randn(3, 4, 2)
    x0 = predict_x0(xt, eps, 0)
    assert x0.abs().max() <= 1
    assert torch.equal(ddpm_step(xt, eps, 0, torch.randn_like(xt)), x0)
    assert torch.equal(ddim_step(xt, eps, 5, -1, eta=1.0, noise=torch.randn_like(xt)), predict_x0(xt, eps, 5))
    # no noise on the step into level 0, and eta = 0 ignores the noise
    assert torch.equal(ddim_step(xt, eps, 1, 0, 1.0, torch.randn_like(xt)), ddim_step(xt, eps, 1, 0, 1.0, None))
    assert torch.equal(ddim_step(xt, eps, 9, 4, 0.0, torch.randn_like(xt)), ddim_step(xt, eps, 9, 4, 0.0, None))
    assert not torch.equal(ddim_step(xt, eps, 9, 4, 0.5, torch.randn_like(xt)), ddim_step(xt, eps, 9, 4, 0.5, None))


def test_ddim_timesteps_paper_variant():
    pairs = ddim_timesteps(15, "quadratic", variant="paper")
    ts = [t for t, _ in pairs]
    assert len(pairs) == 15 and len(set(ts)) == 15 and ts == sorted(ts, reverse=True)
    assert ts[0] == 90 and pairs[-1] == (0, -1)
    assert all(t_next == nxt for (_, t_next), nxt in zip(pairs, ts[1:] + [-1]))
    assert ddim_timesteps(15, "quadratic", variant="paper") == pairs  # deterministic
    assert ddim_timesteps(100, "uniform") == [(t, t - 1) for t in range(99, -1, -1)]


def test_ddim_timesteps_official_variant():
    base = {0, 1, 4, 7, 11, 16, 22, 29, 37, 45, 55, 66, 77, 90}
    runs = [ddim_timesteps(15, variant="official", generator=torch.Generator().manual_seed(s)) for s in range(6)]
    for pairs in runs:
        ts = [t for t, _ in pairs]
        assert len(pairs) == 15 and pairs[-2:] == [(1, 0), (1, 0)]
        assert set(ts[:-1]) | {0} >= base and len(set(ts[:-1]) | {0}) == 15  # one extra unused step
        assert ts == sorted(ts, reverse=True)
    assert len({tuple(p) for p in runs}) > 1  # the extra step comes from the generator
    again = ddim_timesteps(15, variant="official", generator=torch.Generator().manual_seed(0))
    assert again == runs[0]


class GaussianEps:
    """Exact noise predictor for 1-D data ~ N(mu, s^2):
    E[eps | x_t] = sqrt(1 - a) (x_t - sqrt(a) mu) / (a s^2 + 1 - a)."""

    horizon, dof = 1, 1

    def __init__(self, mu: float, s: float):
        self.mu, self.s, self.sch = mu, s, get_schedule()

    def __call__(self, x, t, context):
        a = self.sch.abar(t)
        return math.sqrt(1 - a) * (x - math.sqrt(a) * self.mu) / (a * self.s**2 + 1 - a)


def ddpm_output_law(mu: float, s: float) -> tuple[float, float]:
    """Mean and std of the 100-step DDPM output for Gaussian data: every step is affine + Gaussian noise."""
    tab = get_schedule().tables
    mean, var = 0.0, 1.0
    for t in range(99, -1, -1):
        a = tab["alphas_cumprod"][t]
        k = math.sqrt(1 - a) / (a * s * s + 1 - a)
        gain = (
            tab["posterior_mean_coef1"][t] * (1 - math.sqrt(1 - a) * k) / math.sqrt(a) + tab["posterior_mean_coef2"][t]
        )
        offset = tab["posterior_mean_coef1"][t] * math.sqrt(1 - a) * k * mu
        mean, var = gain * mean + offset, gain**2 * var + (tab["posterior_variance"][t] if t > 0 else 0.0)
    return mean, math.sqrt(var)


def test_ddim_eta1_all_steps_matches_ddpm_in_distribution():
    mu, s, n = 0.1, 0.3, 4000
    model = GaussianEps(mu, s)
    ddpm = sample(model, {}, n, sampler="ddpm", generator=torch.Generator().manual_seed(0)).double().flatten()
    ddim = (
        sample(
            model,
            {},
            n,
            sampler="ddim",
            steps=100,
            schedule="uniform",
            eta=1.0,
            generator=torch.Generator().manual_seed(1),
        )
        .double()
        .flatten()
    )
    law_mean, law_std = ddpm_output_law(mu, s)
    for x in (ddpm.numpy(), ddim.numpy()):
        assert scipy.stats.kstest(x, "norm", args=(law_mean, law_std)).pvalue > 0.01
        # and both are close to the data distribution itself (DDPM's fixed variance shrinks it a little)
        assert abs(x.mean() - mu) < 0.02 and abs(x.std() / s - 1) < 0.08
    assert scipy.stats.ks_2samp(ddpm.numpy(), ddim.numpy()).pvalue > 0.01
    # deterministic DDIM (the probability-flow ODE) with all steps recovers the data distribution too
    ode = sample(model, {}, n, steps=100, schedule="uniform", eta=0.0, generator=torch.Generator().manual_seed(2))
    assert scipy.stats.kstest(ode.double().flatten().numpy(), "norm", args=(mu, s)).pvalue > 0.01


def test_sampling_is_seeded_and_history_has_every_step():
    model = GaussianEps(0.0, 0.5)
    a, hist = sample(model, {}, 7, generator=torch.Generator().manual_seed(3), return_history=True, eta=0.5)
    b = sample(model, {}, 7, generator=torch.Generator().manual_seed(3), eta=0.5)
    assert torch.equal(a, b) and len(hist) == 16 and torch.equal(hist[-1], a)


# --- CVAE ------------------------------------------------------------------------------------------------
def test_kl_matches_torch_distributions():
    mu, logvar = torch.randn(6, 32, dtype=torch.float64), torch.randn(6, 32, dtype=torch.float64)
    q = torch.distributions.Normal(mu, (0.5 * logvar).exp())
    p = torch.distributions.Normal(torch.zeros_like(mu), torch.ones_like(mu))
    assert torch.allclose(kl_standard_normal(mu, logvar), torch.distributions.kl_divergence(q, p).sum(-1))


def test_cvae_trains_and_samples_with_ee_context(tmp_path):
    arrays = toy_arrays(n=24, horizon=9, dof=3, ee=True, n_val=4)
    spec = tiny_training(steps=30)
    path = train_model(arrays, "cvae", TINY, spec, seed=0, progress=False, cache=tmp_path)
    meta = json.loads((path.parent / "meta.json").read_text())
    assert meta["final_val_loss"] is not None and "ee_rot" not in meta["normalizers"]["context"]
    model = load_model(path, expect_task="Toy", device="cpu")
    assert isinstance(model.network, CVAE)
    ctx = {k: v[0] for k, v in arrays.context.items()}
    x = model.sample(ctx, 5, generator=torch.Generator().manual_seed(0))
    assert x.shape == (5, 9, 3) and torch.isfinite(x).all()
    terms = model.network.loss_terms(
        torch.zeros(2, 9, 3), model.normalize_context({k: v[:2] for k, v in arrays.context.items()})
    )
    assert torch.allclose(terms["loss"], terms["reconstruction"] + 0.1 * terms["kl"])


# --- training and checkpoints ----------------------------------------------------------------------------
def test_tiny_model_overfits(tmp_path):
    arrays = toy_arrays(n=16)
    spec = TrainingSpec(batch_size=64, steps=300, lr=2e-3, val_every=10**6, checkpoint_every=10**6, ema_start=10**6)
    path = train_model(arrays, "diffusion", TINY, spec, seed=0, progress=False, cache=tmp_path)
    trained = load_model(path, device="cpu")
    x0 = trained.x_normalizer.normalize(torch.as_tensor(arrays.x)).repeat(64, 1, 1)
    ctx = {k: v.repeat(64, 1) for k, v in trained.normalize_context(arrays.context).items()}

    def loss(net):
        with torch.no_grad():
            return float(net.loss(x0, ctx, torch.Generator().manual_seed(1)))

    assert loss(train_module._init_network("diffusion", arrays, TINY, 0)) > 10 * loss(trained.network)


def test_checkpoint_round_trip_gives_identical_samples(trained):
    arrays, path, cache = trained
    ctx = {k: v[0] for k, v in arrays.context.items()}
    a = load_model(path, expect_task="Toy", expect_parametrization="bspline", device="cpu")
    b = load_model(path.parent, device="cpu")  # the folder works too
    sa = a.sample(ctx, 6, generator=torch.Generator().manual_seed(0), eta=0.5)
    sb = b.sample(ctx, 6, generator=torch.Generator().manual_seed(0), eta=0.5)
    assert torch.equal(sa, sb) and sa.shape == (6, 8, 2)
    assert not torch.equal(sa, b.sample(ctx, 6, generator=torch.Generator().manual_seed(1), eta=0.5))
    # raw-unit samples = unnormalized network samples with the normalized context
    net_out = b.network.sample(b.normalize_context(ctx), 6, generator=torch.Generator().manual_seed(0), eta=0.5)
    assert torch.allclose(sa, b.x_normalizer.unnormalize(net_out))
    # a second call finds the model instead of training again
    again = train_model(arrays, "diffusion", TINY, tiny_training(), seed=0, progress=False, cache=cache)
    assert again == path and not (path.parent / "last.pt").exists()
    meta = a.meta
    assert meta["task_hash"] == "task0" and meta["dataset_hash"] == "data0" and meta["step"] == 40
    assert meta["provenance"]["mpd_version"]


def test_same_seed_same_weights_and_resume_is_exact(tmp_path):
    arrays = toy_arrays(n_val=4)
    spec = tiny_training()
    full = train_model(arrays, "diffusion", TINY, spec, seed=3, progress=False, cache=tmp_path / "a")
    again = train_model(arrays, "diffusion", TINY, spec, seed=3, progress=False, cache=tmp_path / "b")
    partial = train_model(arrays, "diffusion", TINY, spec, seed=3, progress=False, cache=tmp_path / "c", stop_after=23)
    assert partial.name == "last.pt" and read_checkpoint(partial)["step"] == 23
    resumed = train_model(arrays, "diffusion", TINY, spec, seed=3, progress=False, cache=tmp_path / "c")
    ref = read_checkpoint(full)
    for other in (read_checkpoint(again), read_checkpoint(resumed)):
        for key in ("weights", "ema_weights"):
            assert all(torch.equal(ref[key][k], other[key][k]) for k in ref[key])
        assert other["history"] == ref["history"]


def test_ctrl_c_saves_a_state_that_resumes_exactly(tmp_path, monkeypatch):
    handler_before = signal.getsignal(signal.SIGINT)
    arrays = toy_arrays()
    spec = tiny_training(steps=20, val_every=1000)
    ref = read_checkpoint(train_model(arrays, "diffusion", TINY, spec, seed=1, progress=False, cache=tmp_path / "a"))
    original = step_module.apply_ema
    calls = []

    def ema_then_ctrl_c(ema_params, params, w):
        original(ema_params, params, w)
        calls.append(w)
        if sum(1 for x in calls if x) == 2:  # the second EMA update: step 10
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(step_module, "apply_ema", ema_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt, match="step 10"):
        train_model(arrays, "diffusion", TINY, spec, seed=1, progress=False, cache=tmp_path / "b")
    monkeypatch.setattr(step_module, "apply_ema", original)
    resumed = read_checkpoint(
        train_model(arrays, "diffusion", TINY, spec, seed=1, progress=False, cache=tmp_path / "b")
    )
    assert all(torch.equal(ref["ema_weights"][k], resumed["ema_weights"][k]) for k in ref["ema_weights"])
    assert signal.getsignal(signal.SIGINT) is handler_before


def test_list_models(trained):
    arrays, path, cache = trained
    found = list_models("Toy", cache=cache)
    assert [m["path"] for m in found] == [str(path)]
    assert found[0]["steps"] == 40 and found[0]["steps_per_s"] > 0 and found[0]["n_val"] == 4
    assert list_models("Other", cache=cache) == []


def test_wrong_task_or_parametrization_is_a_clear_error(trained):
    _, path, _ = trained
    with pytest.raises(ConfigError, match=r"model\.pt.*task 'Toy', expected 'EnvSimple2D"):
        load_model(path, expect_task="EnvSimple2D-RobotPointMass2D")
    with pytest.raises(ConfigError, match=r"parametrization 'bspline', expected 'waypoints'"):
        load_model(path, expect_parametrization="waypoints")


def test_truncated_or_foreign_file_is_a_clear_error(trained, tmp_path):
    _, path, _ = trained
    data = path.read_bytes()
    cases = {"truncated.pt": data[: len(data) // 2], "garbage.pt": b"not a checkpoint at all"}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ConfigError, match=rf"{name}: .*truncated or corrupted") as e:
            load_model(tmp_path / name)
        assert e.value.__cause__ is None and e.value.__suppress_context__
    torch.save({"weights": {}}, tmp_path / "foreign.pt")
    with pytest.raises(ConfigError, match="not an mpd model checkpoint"):
        load_model(tmp_path / "foreign.pt")
    with pytest.raises(ConfigError, match="not found"):
        load_model(tmp_path / "missing.pt")


def test_cvae_kl_warmup_scales_the_kl_term_and_enters_only_the_cvae_identity(tmp_path):
    """``training.kl_warmup_steps``: the loss is reconstruction + scale x beta x KL (checked against the terms), the
    training uses it (its first steps differ from a run without), and it changes a CVAE's identity only: the
    diffusion identity and a CVAE with the default 0 keep the identity they had before the field existed."""
    arrays = toy_arrays(n=24, horizon=9, dof=3, ee=True, n_val=4)
    path = train_model(arrays, "cvae", TINY, tiny_training(steps=4), seed=0, progress=False, cache=tmp_path / "a")
    model = load_model(path, device="cpu")
    ctx = model.normalize_context({k: v[:4] for k, v in arrays.context.items()})
    x = torch.randn(4, 9, 3, generator=torch.Generator().manual_seed(1))
    for scale in (0.0, 0.25, 1.0):
        t = model.network.loss_terms(x, ctx, torch.Generator().manual_seed(2), kl_scale=scale)
        assert t["kl"] > 0 and torch.allclose(t["loss"], t["reconstruction"] + scale * 0.1 * t["kl"])
    warm = train_model(
        arrays, "cvae", TINY, tiny_training(steps=4, kl_warmup_steps=3), seed=0, progress=False, cache=tmp_path / "b"
    )
    a, b = (torch.load(p, weights_only=False)["weights"] for p in (path, warm))
    assert any(not torch.equal(a[k], b[k]) for k in a)
    ident = {
        (kind, w): model_identity("d", kind, "bspline", {}, TINY, tiny_training(kl_warmup_steps=w), 0)
        for kind in ("diffusion", "cvae")
        for w in (0, 100)
    }
    assert ident["diffusion", 0] == ident["diffusion", 100] and ident["cvae", 0] != ident["cvae", 100]
    assert ident["cvae", 0] == model_identity("d", "cvae", "bspline", {}, TINY, tiny_training(), 0)
    with pytest.raises(ValueError, match="kl_warmup_steps"):
        train_model(arrays, "cvae", TINY, tiny_training(kl_warmup_steps=-1), progress=False, cache=tmp_path / "c")


def test_identity_changes_with_every_setting():
    base = dict(
        dataset_hash="d",
        kind="diffusion",
        parametrization="bspline",
        parametrization_settings={"n": 16},
        model_spec=TINY,
        training_spec=tiny_training(),
        seed=0,
    )
    variants = [
        dict(dataset_hash="e"),
        dict(kind="cvae"),
        dict(parametrization="waypoints"),
        dict(parametrization_settings={"n": 17}),
        dict(model_spec=dataclasses.replace(TINY, context_dim=32)),
        dict(model_spec=dataclasses.replace(TINY, unet_dim_mults=[1, 2, 4])),
        dict(training_spec=tiny_training(steps=41)),
        dict(training_spec=tiny_training(lr=2e-3)),
        dict(seed=1),
    ]
    ids = {model_identity(**base)} | {model_identity(**{**base, **v}) for v in variants}
    assert len(ids) == len(variants) + 1
    assert model_identity(**base) == model_identity(**base)


def test_training_arrays_reject_bad_input():
    good = toy_arrays()
    with pytest.raises(ValueError, match=r"context\['q_goal'\].*shape"):
        dataclasses.replace(good, context={"q_start": good.context["q_start"], "q_goal": np.zeros((16, 3))})
    with pytest.raises(ValueError, match="match no context kind"):
        dataclasses.replace(good, context={"q_start": good.context["q_start"]})
    with pytest.raises(ValueError, match="no training samples"):
        dataclasses.replace(good, split=np.ones(16, np.int8))
    with pytest.raises(ValueError, match="NaN"):
        dataclasses.replace(good, x=np.full_like(good.x, np.nan))
    with pytest.raises(ValueError, match="may only contain"):
        dataclasses.replace(good, parametrization="b/spline")
    with pytest.raises(ValueError, match="unknown model kind"):
        train_model(good, "gan", TINY, tiny_training(), progress=False)


def test_build_network_kinds():
    assert isinstance(build_network("diffusion", 2, 8, "goal_joint_position", TINY), DiffusionModel)
    assert isinstance(build_network("cvae", 2, 8, "goal_joint_position", TINY), CVAE)


def test_learning_rate_schedules():
    import dataclasses
    import math

    from mpd.models.train import learning_rate
    from mpd.tasks.spec import TrainingSpec

    const = TrainingSpec(batch_size=8, steps=100, lr=3e-4)
    assert all(learning_rate(const, s) == 3e-4 for s in (0, 50, 99))
    cos = dataclasses.replace(const, lr=1e-3, lr_schedule="cosine", warmup_steps=10, lr_min_ratio=0.1)
    assert learning_rate(cos, 0) == pytest.approx(1e-4 * (0.1 + 0.9 * 0.5 * (1 + math.cos(0))))
    assert learning_rate(cos, 9) == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 9 / 99))))
    assert learning_rate(cos, 99) == pytest.approx(1e-4)
    lrs = [learning_rate(cos, s) for s in range(10, 100)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))


# --- fidelity to the authors' networks ----------------------------------------------------------------------------
@pytest.mark.parametrize("n_layers", [0, 1, 2])
def test_context_mlp_has_n_layers_plus_one_hidden_layers(n_layers):
    """The authors' MLP(n_layers): Linear(in, h), ReLU, n_layers x [Linear(h, h), ReLU], Linear(h, out), recomputed
    here with plain matrix products on the encoder's own weights."""
    from mpd.models.context import ContextEncoder

    enc = ContextEncoder("goal_joint_position", 3, 8, n_layers).double()
    linears = [m for m in enc.joints if isinstance(m, torch.nn.Linear)]
    assert len(linears) == n_layers + 2  # n_layers + 1 hidden layers and the output layer
    assert len([m for m in enc.combine if isinstance(m, torch.nn.Linear)]) == 3  # combining MLP: n_layers = 1
    x = {"q_start": torch.randn(5, 3, dtype=torch.float64), "q_goal": torch.randn(5, 3, dtype=torch.float64)}

    def by_hand(layers, h):
        for k, lin in enumerate(layers):
            h = h @ lin.weight.T + lin.bias
            if k < len(layers) - 1:
                h = h.clamp_min(0)
        return h

    h = by_hand(linears, torch.cat([x["q_start"], x["q_goal"]], -1))
    ref = by_hand([m for m in enc.combine if isinstance(m, torch.nn.Linear)], h)
    assert torch.allclose(enc(x), ref, atol=1e-12)


def test_cvae_logvar_soft_clip_loss_and_reparametrization_by_hand():
    """The authors' CVAE: log-variance soft-clipped by lo + softplus(hi - softplus(hi - v) - lo) into (-7, 2); loss =
    mean over the batch of ||x_rec - x||_F + 0.1 KL; z = mu + exp(logvar / 2) eps (not the authors' 0.5 exp(logvar))."""
    from mpd.models.cvae import soft_clip

    v = torch.linspace(-30, 30, 601, dtype=torch.float64)
    sp = lambda u: np.log1p(np.exp(-np.abs(u))) + np.maximum(u, 0)  # noqa: E731
    vn = v.numpy()
    assert np.allclose(soft_clip(v).numpy(), -7 + sp(2 - sp(2 - vn) + 7), atol=1e-12)
    assert soft_clip(v).min() >= -7 and soft_clip(v).max() < 2 + 2e-4  # softplus(9) = 9.0001
    assert abs(float(soft_clip(torch.tensor(-2.5))) + 2.5) < 0.02  # near identity well inside the range

    torch.manual_seed(0)
    net = CVAE(3, 9, "goal_joint_position", TINY).double()
    x = torch.randn(4, 9, 3, dtype=torch.float64)
    ctx = {"q_start": torch.randn(4, 3, dtype=torch.float64), "q_goal": torch.randn(4, 3, dtype=torch.float64)}
    with torch.no_grad():
        terms = net.loss_terms(x, ctx, torch.Generator().manual_seed(5))
        emb = net.context_encoder(ctx)
        mu, logvar = net.encode(x, emb)
    eps = torch.randn(4, net.latent_dim, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    z = mu + torch.exp(0.5 * logvar) * eps
    with torch.no_grad():
        rec = net.decode(z, emb)
    frob = np.sqrt(((rec - x).detach().numpy() ** 2).sum(axis=(1, 2)))
    kl = 0.5 * (mu**2 + logvar.exp() - 1 - logvar).sum(-1)
    assert float(terms["reconstruction"]) == pytest.approx(frob.mean(), rel=1e-10)
    assert float(terms["loss"]) == pytest.approx(frob.mean() + 0.1 * float(kl.mean()), rel=1e-10)
    # the latent-to-bottleneck map is the authors' MLP(n_layers = 1): two hidden ReLU layers of the mid width
    lin = [m for m in net.from_latent if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in lin] == [
        (32, net.bottleneck[0]),
        (net.bottleneck[0], net.bottleneck[0]),
        (net.bottleneck[0], net.bottleneck[0] * net.bottleneck[1]),
    ]


def test_unnormalize_clips_to_the_data_range_and_the_gradient_is_that_of_the_clip():
    """As the authors' limits normalizer: x_norm is clipped to [-1, 1] before unnormalizing, and the chain rule
    through it (checked against autograd of clamp) zeroes the gradient of entries outside the range."""
    norm = Normalizer(np.array([-2.0, 0.0]), np.array([2.0, 10.0]))
    x = torch.tensor([[[-1.5, 0.2], [0.3, 1.7], [0.99, -0.999]]], dtype=torch.float64, requires_grad=True)
    raw = norm.unnormalize(x)
    assert torch.allclose(raw, torch.tensor([[[-2.0, 6.0], [0.6, 10.0], [1.98, 0.005]]], dtype=torch.float64))
    assert torch.allclose(norm.unnormalize(x, clip=False)[0, 0], torch.tensor([-3.0, 6.0], dtype=torch.float64))
    w = torch.tensor([[[1.0, -2.0], [3.0, 0.5], [-1.0, 4.0]]], dtype=torch.float64)
    cost = (w * raw**2).sum()
    (g_auto,) = torch.autograd.grad(cost, x)
    g_raw = 2 * w * raw.detach()
    assert torch.allclose(norm.grad_to_normalized(g_raw, x.detach()), g_auto)
    assert torch.allclose(norm.grad_to_normalized(g_raw), g_raw * torch.tensor([2.0, 5.0], dtype=torch.float64))


# --- training recipes: wsd trunks, min-SNR weighting, bf16, identity compatibility ------------------------------------
def test_wsd_budget_resumed_from_a_trunk_equals_the_same_budget_trained_alone(tmp_path):
    """A wsd model of 40 steps trained after a 20-step one resumes from the 20-step run's stable-phase snapshot (step
    16) and ends bit-identical to the 40-step model trained from scratch in another cache."""
    from mpd.models import train as tr

    arrays = toy_arrays(n_val=4)
    short = tiny_training(steps=20, lr_schedule="wsd", decay_fraction=0.2, warmup_steps=4, checkpoint_every=8)
    long = dataclasses.replace(short, steps=40)
    assert tr.stable_steps(short) == 16 and tr.stable_steps(long) == 32
    key = tr.trunk_identity("data0", "diffusion", "bspline", {}, TINY, short, 3)
    assert key == tr.trunk_identity("data0", "diffusion", "bspline", {}, TINY, long, 3)
    assert key != tr.trunk_identity("data0", "diffusion", "bspline", {}, TINY, dataclasses.replace(long, lr=2e-3), 3)
    train_model(arrays, "diffusion", TINY, short, seed=3, progress=False, cache=tmp_path / "a")
    snaps = sorted(p.name for p in (tmp_path / "a" / "models" / "Toy" / "trunks").glob("*/step-*.pt"))
    assert snaps == ["step-000000008.pt", "step-000000016.pt"]  # every checkpoint_every and the stable end
    via_trunk = read_checkpoint(
        train_model(arrays, "diffusion", TINY, long, seed=3, progress=False, cache=tmp_path / "a")
    )
    alone = read_checkpoint(train_model(arrays, "diffusion", TINY, long, seed=3, progress=False, cache=tmp_path / "b"))
    assert via_trunk["resumed_from_trunk_step"] == 16 and "resumed_from_trunk_step" not in alone
    for key in ("weights", "ema_weights"):
        assert all(torch.equal(alone[key][k], via_trunk[key][k]) for k in alone[key])
    assert [h["train_loss"] for h in alone["history"]] == [h["train_loss"] for h in via_trunk["history"]]


def test_constant_budget_started_from_a_longer_runs_checkpoint_equals_it_trained_alone(tmp_path):
    """mpd train --from: a 30-step constant-schedule model started from step 20 of a 60-step run's last.pt (in
    another cache) ends bit-identical to the 30-step model trained from step 0, and records where it started."""
    arrays = toy_arrays(n_val=4)
    long, short = tiny_training(steps=60), tiny_training(steps=30)
    last = train_model(arrays, "diffusion", TINY, long, seed=3, progress=False, cache=tmp_path / "a", stop_after=20)
    ckpt = shutil.copy(last, tmp_path / "long-20.pt")
    started = read_checkpoint(
        train_model(arrays, "diffusion", TINY, short, seed=3, progress=False, cache=tmp_path / "b", start_from=ckpt)
    )
    alone = read_checkpoint(train_model(arrays, "diffusion", TINY, short, seed=3, progress=False, cache=tmp_path / "c"))
    assert started["identity"] == alone["identity"] != read_checkpoint(ckpt)["identity"]
    assert started["started_from"] == {"identity": read_checkpoint(ckpt)["identity"], "step": 20, "file": "long-20.pt"}
    assert "started_from" not in alone
    for key in ("weights", "ema_weights"):
        assert all(torch.equal(alone[key][k], started[key][k]) for k in alone[key])
    # a budget that ends at the checkpoint's step is that state, finished (no step to take)
    path = train_model(
        arrays,
        "diffusion",
        TINY,
        tiny_training(steps=20),
        seed=3,
        progress=False,
        cache=tmp_path / "d",
        start_from=ckpt,
    )
    at, source = read_checkpoint(path), read_checkpoint(ckpt)
    assert at["started_from"]["step"] == 20 and at["history"][-1]["step"] == 20
    assert json.loads((path.parent / "meta.json").read_text())["steps_per_s"] is None  # no step, no throughput
    assert all(torch.equal(at["ema_weights"][k], source["ema_weights"][k]) for k in source["ema_weights"])
    # what does not qualify is named: the budget passed, another learning rate, the cosine schedule
    record = {k: started[k] for k in train_module.SAME_TRAINING_FIELDS} | {"training_spec": started["training_spec"]}
    with pytest.raises(ConfigError, match="step: is 20, past this training's 10 steps"):
        train_module.start_state(ckpt, record, tiny_training(steps=10), torch.device("cpu"))
    other = record | {"training_spec": {**record["training_spec"], "lr": 2e-3}}
    with pytest.raises(ConfigError, match=r"training_spec: differs in more than the budget: lr = 0.001 \(this"):
        train_module.start_state(ckpt, other, tiny_training(steps=30, lr=2e-3), torch.device("cpu"))
    with pytest.raises(ConfigError, match="seed: is 3, this training's is 4"):
        train_module.start_state(ckpt, record | {"seed": 4}, short, torch.device("cpu"))
    with pytest.raises(ConfigError, match="cosine"):
        train_module.start_state(ckpt, record, tiny_training(steps=30, lr_schedule="cosine"), torch.device("cpu"))


def test_a_wsd_budget_started_from_a_constant_runs_checkpoint_equals_it_trained_alone(tmp_path):
    """mpd train --from across schedules: a constant run is a wsd run's stable phase, step for step, so a 40-step wsd
    budget (stable to step 30, then a decay to another floor than the constant run records) started from step 20 of
    a 60-step constant run ends bit-identical to it trained from step 0. What does not qualify is named: a step past
    the wsd run's stable phase, another warm-up, a constant budget from a state in a wsd run's decay (one from its
    stable phase equals the constant budget trained alone)."""
    arrays = toy_arrays(n_val=4)
    const = tiny_training(steps=60)
    wsd = tiny_training(steps=40, lr_schedule="wsd", decay_fraction=0.25, lr_min_ratio=0.05)
    last = train_model(arrays, "diffusion", TINY, const, seed=3, progress=False, cache=tmp_path / "a", stop_after=20)
    ckpt = shutil.copy(last, tmp_path / "const-20.pt")
    started = read_checkpoint(
        train_model(arrays, "diffusion", TINY, wsd, seed=3, progress=False, cache=tmp_path / "b", start_from=ckpt)
    )
    alone = read_checkpoint(train_model(arrays, "diffusion", TINY, wsd, seed=3, progress=False, cache=tmp_path / "c"))
    assert started["identity"] == alone["identity"] and started["started_from"]["step"] == 20
    for key in ("weights", "ema_weights"):
        assert all(torch.equal(alone[key][k], started[key][k]) for k in alone[key])
    assert [h["train_loss"] for h in alone["history"]] == [h["train_loss"] for h in started["history"]]
    record = {k: started[k] for k in train_module.SAME_TRAINING_FIELDS} | {"training_spec": started["training_spec"]}
    at35 = shutil.copy(
        train_model(arrays, "diffusion", TINY, const, seed=3, progress=False, cache=tmp_path / "e", stop_after=35),
        tmp_path / "const-35.pt",
    )
    with pytest.raises(ConfigError, match=r"step: is 35, past this training's 40 steps \(stable phase to 30\)"):
        train_module.start_state(at35, record, wsd, torch.device("cpu"))
    warm = record | {"training_spec": {**record["training_spec"], "warmup_steps": 4}}
    with pytest.raises(ConfigError, match="differs in more than the budget: warmup_steps = 0"):
        train_module.start_state(ckpt, warm, dataclasses.replace(wsd, warmup_steps=4), torch.device("cpu"))
    # the reverse: a constant budget from a wsd run's stable phase equals it trained alone
    stable = shutil.copy(
        train_model(arrays, "diffusion", TINY, wsd, seed=3, progress=False, cache=tmp_path / "f", stop_after=20),
        tmp_path / "wsd-20.pt",
    )
    short = tiny_training(steps=30)
    back = read_checkpoint(
        train_model(arrays, "diffusion", TINY, short, seed=3, progress=False, cache=tmp_path / "g", start_from=stable)
    )
    plain = read_checkpoint(train_model(arrays, "diffusion", TINY, short, seed=3, progress=False, cache=tmp_path / "h"))
    assert back["identity"] == plain["identity"] and back["started_from"]["step"] == 20
    assert all(torch.equal(plain["ema_weights"][k], back["ema_weights"][k]) for k in plain["ema_weights"])
    in_decay = train_model(arrays, "diffusion", TINY, wsd, seed=3, progress=False, cache=tmp_path / "d", stop_after=35)
    const_record = record | {"training_spec": read_checkpoint(ckpt)["training_spec"]}
    with pytest.raises(ConfigError, match="is 35, in its own run's decay"):
        train_module.start_state(in_decay, const_record, const, torch.device("cpu"))


def test_wsd_learning_rate_is_flat_then_decays_to_the_floor():
    from mpd.models.train import learning_rate

    ts = TrainingSpec(batch_size=8, steps=100, lr=1e-3, lr_schedule="wsd", warmup_steps=10, decay_fraction=0.3)
    assert learning_rate(ts, 0) == pytest.approx(1e-4)
    assert all(learning_rate(ts, s) == pytest.approx(1e-3) for s in range(9, 70))
    lrs = [learning_rate(ts, s) for s in range(70, 100)]
    assert all(a > b for a, b in zip(lrs, lrs[1:])) and lrs[-1] == pytest.approx(1e-3 * ts.lr_min_ratio)
    assert lrs[0] == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi / 30))))


def test_min_snr_loss_weights_each_sample_by_min_snr_over_snr():
    """The weighted loss recomputed by hand from the same draws (t and noise from a generator of the same seed)."""
    from mpd.models.diffusion import q_sample, randint, randn

    torch.manual_seed(0)
    net = DiffusionModel(2, 8, "goal_joint_position", TINY)
    x0 = torch.rand(64, 8, 2) * 2 - 1
    ctx = {"q_start": torch.rand(64, 2), "q_goal": torch.rand(64, 2)}
    got = net.loss(x0, ctx, torch.Generator().manual_seed(5), weighting="min_snr", min_snr_gamma=2.0)
    g = torch.Generator().manual_seed(5)
    t = randint(100, (64,), g, x0.device)
    noise = randn((64, 8, 2), g, x0.device, x0.dtype)
    abar = torch.as_tensor(net.schedule.tables["alphas_cumprod"], dtype=torch.float32)[t]
    snr = abar / (1 - abar)
    w = torch.minimum(snr, torch.full_like(snr, 2.0)) / snr
    err = ((net(q_sample(x0, t, noise, net.schedule), t, ctx) - noise) ** 2).mean((1, 2))
    assert torch.allclose(got, (w * err).mean(), rtol=1e-5)
    assert (w < 1).any() and (w == 1).any()  # both regimes are in the batch
    uniform = net.loss(x0, ctx, torch.Generator().manual_seed(5))
    assert torch.allclose(uniform, err.mean(), rtol=1e-5)


def test_goal_row_weight_is_a_row_weighted_mean_of_the_squared_errors():
    """An end-effector-goal model's loss with goal_row_weight w, recomputed by hand from the same draws: per sample,
    (sum of the other rows' mean squared errors + w x the last row's) / (H - 1 + w); with min-SNR on top too."""
    from mpd.models.diffusion import q_sample, randint, randn

    torch.manual_seed(0)
    net = DiffusionModel(3, 8, "goal_ee_pose", TINY)
    x0 = torch.rand(32, 8, 3) * 2 - 1
    ctx = {"q_start": torch.rand(32, 3), "ee_pos": torch.rand(32, 3), "ee_rot": torch.eye(3).expand(32, 3, 3)}
    g = torch.Generator().manual_seed(7)
    t = randint(100, (32,), g, x0.device)
    noise = randn((32, 8, 3), g, x0.device, x0.dtype)
    with torch.no_grad():
        row_err = ((net(q_sample(x0, t, noise, net.schedule), t, ctx) - noise) ** 2).mean(2)  # (32, 8)
        by_hand = (row_err[:, :-1].sum(1) + 6.0 * row_err[:, -1]) / (7 + 6.0)
        got = net.loss(x0, ctx, torch.Generator().manual_seed(7), goal_row_weight=6.0)
        assert torch.allclose(got, by_hand.mean(), rtol=1e-5)
        assert not torch.allclose(got, row_err.mean(), rtol=1e-3)  # the weight changes the loss
        abar = torch.as_tensor(net.schedule.tables["alphas_cumprod"], dtype=torch.float32)[t]
        snr = abar / (1 - abar)
        w = torch.minimum(snr, torch.full_like(snr, 3.0)) / snr
        both = net.loss(x0, ctx, torch.Generator().manual_seed(7), weighting="min_snr", min_snr_gamma=3.0,
                        goal_row_weight=6.0)  # fmt: skip
        assert torch.allclose(both, (w * by_hand).mean(), rtol=1e-5)
        plain = net.loss(x0, ctx, torch.Generator().manual_seed(7), goal_row_weight=1.0)
        assert torch.allclose(plain, row_err.mean(), rtol=1e-5)


def test_goal_row_weight_needs_an_end_effector_goal_and_is_not_part_of_a_cvae(tmp_path):
    from mpd.models.train import model_identity

    ts = tiny_training()
    weighted = dataclasses.replace(ts, goal_row_weight=8.0)
    assert model_identity("h", "cvae", "bspline", {}, TINY, weighted, 0) == model_identity(
        "h", "cvae", "bspline", {}, TINY, ts, 0
    )
    with pytest.raises(ValueError, match="goal_row_weight = 8.0: Toy has a joint-space goal"):
        train_model(toy_arrays(), "diffusion", TINY, weighted, progress=False, cache=tmp_path)
    ee = toy_arrays(ee=True)
    a = read_checkpoint(train_model(ee, "diffusion", TINY, ts, progress=False, cache=tmp_path))
    b = read_checkpoint(train_model(ee, "diffusion", TINY, weighted, progress=False, cache=tmp_path))
    assert a["identity"] != b["identity"] and b["training_spec"]["goal_row_weight"] == 8.0
    assert any(not torch.equal(a["weights"][k], b["weights"][k]) for k in a["weights"])
    c = read_checkpoint(train_model(ee, "cvae", TINY, weighted, progress=False, cache=tmp_path))
    assert c["training_spec"]["goal_row_weight"] == 1.0  # the CVAE trains as without it


def test_goal_head_starts_as_the_unet_alone_and_corrects_only_the_last_row():
    from mpd.models.train import model_identity

    torch.manual_seed(0)
    headed = DiffusionModel(3, 8, "goal_ee_pose", dataclasses.replace(TINY, goal_head_width=32))
    plain = DiffusionModel(3, 8, "goal_ee_pose", TINY)
    missing, unexpected = plain.load_state_dict(headed.state_dict(), strict=False)
    assert not missing and unexpected and all(k.startswith("goal_head.") for k in unexpected)
    x = torch.randn(6, 8, 3)
    ctx = {"q_start": torch.rand(1, 3), "ee_pos": torch.rand(1, 3), "ee_rot": torch.eye(3)[None]}
    t = torch.tensor([0, 5, 20, 50, 80, 99])
    with torch.no_grad():
        assert torch.equal(headed(x, t, ctx), plain(x, t, ctx))  # a zero output layer: the U-Net's prediction
        headed.goal_head.net[-1].bias.fill_(0.5)
        diff = headed(x, t, ctx) - plain(x, t, ctx)
    assert torch.equal(diff[:, :-1], torch.zeros_like(diff[:, :-1])) and torch.allclose(diff[:, -1], torch.tensor(0.5))
    # the last row's head output depends on that row's noisy values, the step and the context
    loss = headed(x.requires_grad_(), t, ctx)[:, -1].sum()
    loss.backward()
    assert x.grad[:, -1].abs().sum() > 0
    with pytest.raises(ValueError, match="goal_head_width = 32: a goal head needs an end-effector-goal task"):
        DiffusionModel(3, 8, "goal_joint_position", dataclasses.replace(TINY, goal_head_width=32))
    # identities: no head is the old identity, a head is another model, and the CVAE ignores it
    ts = tiny_training()
    with_head = dataclasses.replace(TINY, goal_head_width=32)
    assert model_identity("h", "diffusion", "bspline", {}, with_head, ts, 0) != model_identity(
        "h", "diffusion", "bspline", {}, TINY, ts, 0
    )
    assert model_identity("h", "cvae", "bspline", {}, with_head, ts, 0) == model_identity(
        "h", "cvae", "bspline", {}, TINY, ts, 0
    )


def test_he_context_init_keeps_the_context_visible_where_the_default_erases_it():
    """The Panda's context MLPs (context_dim 128, 2 layers) on random normalized contexts: under PyTorch's default init
    the embedding barely varies over contexts (the measurement behind ModelSpec.context_init); He init: weights of
    std sqrt(2 / fan_in), zero biases, and an embedding that varies."""
    from mpd.models.context import ContextEncoder
    from mpd.models.train import model_identity

    torch.manual_seed(0)
    ctx = {
        "q_start": torch.rand(2048, 7) * 2 - 1,
        "ee_pos": torch.rand(2048, 3) * 2 - 1,
        "ee_rot": torch.as_tensor(scipy.stats.special_ortho_group.rvs(3, size=2048, random_state=0)).float(),
    }
    spread = {}
    for init in ("default", "he"):
        enc = ContextEncoder("goal_ee_pose", 7, 128, 2, init)
        with torch.no_grad():
            spread[init] = float(enc(ctx).std(0).mean())
        if init == "he":
            for layer in enc.modules():
                if isinstance(layer, torch.nn.Linear):
                    assert float(layer.bias.abs().max()) == 0.0
                    want = math.sqrt(2 / layer.in_features)
                    assert abs(float(layer.weight.std()) - want) < 0.15 * want
    assert spread["default"] < 0.01 and spread["he"] > 0.1
    # he-zero: He init, then the combining MLP's output weights at zero: the embedding is the (zero) bias for every
    # context while the hidden layer before it varies as under He, so the output layer's gradient is not zero
    torch.manual_seed(0)
    enc = ContextEncoder("goal_ee_pose", 7, 128, 2, "he-zero")
    hidden = enc.combine[:-1]
    with torch.no_grad():
        pose = torch.cat([ctx["ee_pos"], ctx["ee_rot"].flatten(1)], -1)
        h = hidden(torch.cat([enc.joints(ctx["q_start"]), enc.ee_pose(pose)], -1))
        assert float(enc(ctx).abs().max()) == 0.0 and float(h.std(0).mean()) > 0.1
    (enc(ctx) * torch.randn(2048, 128, generator=torch.Generator().manual_seed(1))).sum().backward()
    assert float(enc.combine[-1].weight.grad.abs().max()) > 0.1
    with pytest.raises(ValueError, match="context_init must be one of 'default', 'he', 'he-zero'"):
        ContextEncoder("goal_ee_pose", 7, 16, 1, "xavier")
    ts = tiny_training()
    he = dataclasses.replace(TINY, context_init="he")
    assert DiffusionModel(3, 8, "goal_ee_pose", he).context_encoder.combine[0].bias.abs().max() == 0
    assert model_identity("h", "diffusion", "bspline", {}, he, ts, 0) != model_identity(
        "h", "diffusion", "bspline", {}, TINY, ts, 0
    )
    assert model_identity("h", "cvae", "bspline", {}, he, ts, 0) == model_identity(
        "h", "cvae", "bspline", {}, TINY, ts, 0
    )


def test_a_goal_head_model_trains_saves_and_loads(tmp_path):
    ee = toy_arrays(ee=True, n_val=4)
    spec = dataclasses.replace(TINY, goal_head_width=16)
    path = train_model(ee, "diffusion", spec, tiny_training(), progress=False, cache=tmp_path)
    m = load_model(path)
    assert m.network.goal_head is not None and m.meta["model_spec"]["goal_head_width"] == 16
    assert float(m.network.goal_head.net[-1].weight.abs().sum()) > 0  # it trained
    ctx = m.normalize_context({k: torch.as_tensor(v[:1]) for k, v in ee.context.items()})
    x = m.network.sample(ctx, 4, generator=torch.Generator().manual_seed(0))
    assert x.shape == (4, ee.x.shape[1], ee.x.shape[2]) and torch.isfinite(x).all()


def test_sampler_grid_is_the_ddim_runs_distinct_steps():
    from mpd.models.diffusion import ddim_timesteps, sampler_grid

    grid = sampler_grid()
    assert grid.tolist() == [0, 1, 2, 4, 7, 11, 16, 22, 29, 37, 45, 55, 66, 77, 90]
    for variant in ("paper", "official"):  # every fixed step of either variant is on it (official: + 1 random step)
        steps = {t for t, _ in ddim_timesteps(15, "quadratic", variant=variant, generator=torch.Generator())}
        assert len(steps - set(grid.tolist())) <= (1 if variant == "official" else 0)


def test_sampler_t_sampling_draws_grid_steps_with_the_given_probability():
    """The steps the loss uses, recovered from its forward calls: with p = 0.8 about 80 % + 20 % x 15/100 of them are
    on the grid (a binomial bound), every step of the grid is drawn, and p = 0 is the uniform loss of the same seed."""
    from mpd.models.diffusion import sampler_grid

    torch.manual_seed(0)
    net = DiffusionModel(2, 8, "goal_joint_position", TINY)
    seen = []
    net.unet.register_forward_pre_hook(lambda m, args: seen.append(torch.as_tensor(args[1]).clone()))
    x0 = torch.rand(4000, 8, 2) * 2 - 1
    ctx = {"q_start": torch.rand(4000, 2), "q_goal": torch.rand(4000, 2)}
    grid = sampler_grid()
    with torch.no_grad():
        net.loss(x0, ctx, torch.Generator().manual_seed(3), t_grid=grid, t_grid_fraction=0.8)
        t = seen[-1]
        on_grid = torch.isin(t, grid).float().mean().item()
        expected = 0.8 + 0.2 * len(grid) / 100
        assert abs(on_grid - expected) < 4 * (expected * (1 - expected) / 4000) ** 0.5
        assert set(t.tolist()) >= set(grid.tolist()) and len(set(t.tolist())) > 60  # the uniform part too
        a = net.loss(x0, ctx, torch.Generator().manual_seed(3), t_grid=grid, t_grid_fraction=0.0)
        b = net.loss(x0, ctx, torch.Generator().manual_seed(3))
        assert torch.equal(a, b)
        net.loss(x0, ctx, torch.Generator().manual_seed(3), t_grid=grid, t_grid_fraction=1.0)
        assert torch.isin(seen[-1], grid).all()


def test_bf16_training_is_close_to_fp32_and_has_its_own_identity(tmp_path, monkeypatch):
    monkeypatch.setenv("MPD_BF16", "emulate")  # the bf16 arithmetic on any CPU (emulated where it is not native)
    arrays = toy_arrays(n_val=4)
    fp32 = tiny_training(steps=20)
    bf16 = dataclasses.replace(fp32, precision="bf16")
    a = read_checkpoint(train_model(arrays, "diffusion", TINY, fp32, seed=2, progress=False, cache=tmp_path))
    b = read_checkpoint(train_model(arrays, "diffusion", TINY, bf16, seed=2, progress=False, cache=tmp_path))
    assert a["identity"] != b["identity"]
    assert all(v.dtype == torch.float32 for v in b["weights"].values())
    diffs = [float((a["weights"][k] - b["weights"][k]).abs().max()) for k in a["weights"]]
    assert 0 < max(diffs) < 0.05  # bf16 changes the arithmetic, not the training (lr 1e-3, 20 steps)
    assert abs(a["history"][-1]["train_loss"] - b["history"][-1]["train_loss"]) < 0.1


def test_bf16_training_without_native_bf16_runs_in_fp32(tmp_path, monkeypatch, capsys):
    """On a CPU without bf16 instructions the bf16 setting trains in fp32 (emulated bf16 is ~30x slower): the same
    weights as an fp32 training, the model's own identity, the arithmetic recorded and said once."""
    import mpd.device

    monkeypatch.delenv("MPD_BF16", raising=False)
    monkeypatch.setattr(mpd.device, "native_bf16", lambda device: False)
    arrays = toy_arrays(n_val=4)
    fp32 = tiny_training(steps=20)
    bf16 = dataclasses.replace(fp32, precision="bf16")
    a = read_checkpoint(train_model(arrays, "diffusion", TINY, fp32, seed=2, progress=False, cache=tmp_path))
    pb = train_model(arrays, "diffusion", TINY, bf16, seed=2, progress=False, cache=tmp_path)
    b = read_checkpoint(pb)
    assert a["identity"] != b["identity"]
    assert all(torch.equal(a["weights"][k], b["weights"][k]) for k in a["weights"])
    assert json.loads((pb.parent / "meta.json").read_text())["arithmetic"] == "fp32"
    assert "no native bf16" in capsys.readouterr().out
    monkeypatch.setattr(mpd.device, "native_bf16", lambda device: True)
    assert mpd.device.training_arithmetic("bf16", "cpu") == "bf16"
    assert mpd.device.training_arithmetic("fp32", "cpu") == "fp32"


def test_fields_added_to_the_training_spec_keep_older_identities():
    """The identity of a spec at the defaults of the later fields is the hash of the spec without them (the form every
    model trained before them was stored under)."""
    from mpd.models.train import LATER_TRAINING_FIELDS, NETWORK_VERSION, model_identity
    from mpd.schema import stable_hash, to_dict

    ts = TrainingSpec(batch_size=128, steps=12000, lr=1e-3, lr_schedule="cosine", warmup_steps=200)
    old_form = {k: v for k, v in to_dict(ts).items() if k not in LATER_TRAINING_FIELDS}
    old_net = {k: v for k, v in to_dict(TINY).items() if k not in ("goal_head_width", "context_init")}  # later fields
    expected = stable_hash("h", "diffusion", "bspline", {}, old_net, old_form, 0, {"network_version": NETWORK_VERSION})
    assert model_identity("h", "diffusion", "bspline", {}, TINY, ts, 0) == expected
    for change in (
        {"precision": "bf16"},
        {"loss_weighting": "min_snr"},
        {"decay_fraction": 0.1},
        {"t_sampling": "sampler"},
        {"goal_row_weight": 8.0},
    ):
        assert model_identity("h", "diffusion", "bspline", {}, TINY, dataclasses.replace(ts, **change), 0) != expected


@pytest.mark.parametrize(
    "field, value",
    [
        ("lr_schedule", "linear"), ("decay_fraction", 1.5), ("precision", "fp16"), ("min_snr_gamma", 0),
        ("t_sampling", "grid"), ("t_grid_fraction", 1.5), ("goal_row_weight", 0.0),
    ],
)  # fmt: skip
def test_bad_training_values_are_named(field, value, tmp_path):
    with pytest.raises(ValueError, match=f"training.{field}"):
        train_model(toy_arrays(), "diffusion", TINY, tiny_training(**{field: value}), progress=False, cache=tmp_path)


# --- shipped priors -----------------------------------------------------------------------------------------------
def test_shipped_prior_is_found_by_identity_verified_and_reproduced_bit_for_bit(tmp_path, monkeypatch):
    """Ship a trained model, then a fresh cache gets it without training (same bytes, the lock's hash), and training
    with shipped=False reproduces its EMA weights bit for bit (same CPU type)."""
    from mpd.models import shipped
    from mpd.schema import file_sha256

    monkeypatch.setenv("MPD_PRIORS", str(tmp_path / "priors"))
    arrays = toy_arrays(n_val=4)
    spec = tiny_training(steps=20)
    trained = train_model(arrays, "diffusion", TINY, spec, seed=4, progress=False, cache=tmp_path / "a")
    path = shipped.ship(trained, tmp_path / "priors")
    lock = json.loads(path.with_name(path.name.replace(".pt", ".lock.json")).read_text())
    meta = json.loads((trained.parent / "meta.json").read_text())
    assert path.parent == tmp_path / "priors" / "models" / "Toy"
    old = tmp_path / "old-layout" / "Toy"  # a folder of MPD_PRIORS in the layout before models/
    old.mkdir(parents=True)
    for f in (path, path.with_name(path.name.replace(".pt", ".lock.json"))):
        shutil.copy(f, old / f.name)
    monkeypatch.setenv("MPD_PRIORS", str(tmp_path / "old-layout"))
    assert shipped.find("Toy", "diffusion", "bspline", lock["identity"]) == old / path.name
    monkeypatch.setenv("MPD_PRIORS", str(tmp_path / "priors"))
    assert lock["sha256"] == file_sha256(path) and lock["identity"] == meta["identity"] and lock["steps"] == 20
    for key in ("dataset_hash", "task_hash", "training_spec", "seed", "wall_time_s", "cpu", "git_commit"):
        assert lock[key] not in (None, "") or key == "git_commit"
    assert path.stat().st_size < 0.6 * trained.stat().st_size  # EMA weights once: no second copy, no optimizer

    calls, original = [], train_module.make_optimizer
    monkeypatch.setattr(train_module, "make_optimizer", lambda *a, **k: calls.append(1) or original(*a, **k))
    got = train_model(arrays, "diffusion", TINY, spec, seed=4, progress=False, cache=tmp_path / "b")
    assert not calls, "a shipped prior must not be trained"
    assert file_sha256(got) == lock["sha256"]
    assert json.loads((got.parent / "meta.json").read_text())["source"] == "shipped"
    a, b = load_model(trained), load_model(got)
    assert all(torch.equal(x, y) for x, y in zip(a.network.state_dict().values(), b.network.state_dict().values()))
    monkeypatch.setattr(train_module, "make_optimizer", original)
    again = train_model(arrays, "diffusion", TINY, spec, seed=4, progress=False, cache=tmp_path / "c", shipped=False)
    assert json.loads((again.parent / "meta.json").read_text())["source"] == "trained"
    shipped_ema = torch.load(path, weights_only=True)["ema_weights"]
    retrained = read_checkpoint(again)["ema_weights"]
    assert all(torch.equal(shipped_ema[k], retrained[k]) for k in shipped_ema)


def test_a_bfloat16_shipped_prior_is_half_the_size_and_denoises_like_the_trained_one(tmp_path):
    """Weights rounded to bfloat16 (the Panda-sized priors, whose float32 file exceeds the 10 MB limit): half the
    file, loaded back as exactly the rounded float32 weights, and one denoising step's output within 2 % (relative
    norm) of the trained model's; ``auto`` keeps float32 when it fits; a file too big either way is refused."""
    from mpd.models import shipped

    trained = train_model(
        toy_arrays(n_val=4), "diffusion", TINY, tiny_training(steps=20), seed=4, progress=False, cache=tmp_path / "a"
    )
    p32 = shipped.ship(trained, tmp_path / "p32", weights_dtype="float32")
    p16 = shipped.ship(trained, tmp_path / "p16", weights_dtype="bfloat16")
    lock = json.loads(p16.with_name(p16.name.replace(".pt", ".lock.json")).read_text())
    assert (
        lock["weights_dtype"] == "bfloat16"
        and lock["sha256"] != json.loads(p32.with_name(p32.name.replace(".pt", ".lock.json")).read_text())["sha256"]
    )
    assert p16.stat().st_size < 0.6 * p32.stat().st_size
    a, b = load_model(p32), load_model(p16)
    for (k, x), y in zip(a.network.state_dict().items(), b.network.state_dict().values()):
        assert y.dtype == x.dtype, k
        assert torch.equal(y, x.to(torch.bfloat16).to(x.dtype)), k
    g = torch.Generator().manual_seed(0)
    x = torch.randn(64, 8, 2, generator=g)
    cond = a.normalize_context({"q_start": torch.rand(64, 2, generator=g), "q_goal": torch.rand(64, 2, generator=g)})
    with torch.no_grad():
        e32, e16 = a.network(x, 10, cond), b.network(x, 10, cond)
    rel = float((e32 - e16).norm() / e32.norm())
    assert 0 < rel < 0.02
    auto = shipped.ship(trained, tmp_path / "pa")
    assert json.loads(auto.with_name(auto.name.replace(".pt", ".lock.json")).read_text())["weights_dtype"] == "float32"
    with pytest.raises(ValueError, match="bfloat16"):
        shipped.ship(trained, tmp_path / "px", max_bytes=1000)


def test_a_corrupted_shipped_prior_is_detected_and_retrained(tmp_path, monkeypatch, capfd):
    from mpd.models import shipped

    monkeypatch.setenv("MPD_PRIORS", str(tmp_path / "priors"))
    arrays = toy_arrays(n_val=4)
    spec = tiny_training(steps=10)
    trained = train_model(arrays, "diffusion", TINY, spec, progress=False, cache=tmp_path / "a")
    path = shipped.ship(trained, tmp_path / "priors")
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte inside the weights
    path.write_bytes(bytes(data))
    assert shipped.verify(path)[1].startswith("sha256")
    got = train_model(arrays, "diffusion", TINY, spec, progress=False, cache=tmp_path / "b")
    assert "is not used" in capfd.readouterr().err
    meta = json.loads((got.parent / "meta.json").read_text())
    assert meta["source"] == "trained" and not (got.read_bytes() == bytes(data))
    (tmp_path / "b2").mkdir()
    assert shipped.install("Toy", "diffusion", "bspline", meta["identity"], tmp_path / "b2") is None


def test_bundled_shipped_priors_verify_against_their_locks():
    """Every committed prior matches its lock file (sha256 and size), is within the size limit (the priors issue:
    5 MB for the 2-D tasks; the Panda issue: 10 MB for the Panda ones), and loads."""
    from mpd.models import shipped

    files = sorted(shipped.BUNDLED.glob(f"{shipped.MODELS}/*/*.pt"))
    assert files and not list(shipped.BUNDLED.glob("*/*.pt")), "shipped checkpoints belong in mpd/priors/models/"
    for path in files:
        lock, why = shipped.verify(path)
        assert why is None, f"{path}: {why}"
        limit = 10 if "RobotPanda" in lock["task_name"] else 5
        assert path.stat().st_size <= limit * 2**20, f"{path} is over {limit} MB"
        model = load_model(path, expect_task=lock["task_name"])
        assert model.meta["identity"] == lock["identity"] == path.stem.rsplit("-", 1)[1]


@pytest.mark.parametrize("four_d", [True, False])
def test_one_step_and_context_for_the_batch_runs_the_conditioning_on_one_row(four_d):
    """Sampling (one step and one context for every sample) computes the step embedding and the FiLM layers on one
    row and broadcasts them: the same noise predictions as the step and context given per sample (to float32
    rounding), whether the step is an int, a 0-d or a one-element tensor; a batch of steps still conditions each
    sample on its own."""
    spec = ModelSpec(unet_dim=32, unet_dim_mults=[1, 2, 4, 8], context_dim=128, context_layers=2)
    torch.manual_seed(0)
    model = DiffusionModel(7, 24, "goal_ee_pose", spec).eval()
    model.unet.channels_last_2d = four_d
    g = torch.Generator().manual_seed(1)
    x = torch.randn(6, 24, 7, generator=g)
    ctx1 = {
        "q_start": torch.rand(1, 7, generator=g),
        "ee_pos": torch.rand(1, 3, generator=g),
        "ee_rot": torch.linalg.qr(torch.randn(1, 3, 3, generator=g)).Q,
    }
    ctx6 = {k: v.expand(6, *v.shape[1:]) for k, v in ctx1.items()}
    with torch.no_grad():
        ref = model(x, torch.full((6,), 17), ctx6)  # per sample: the conditioning on 6 rows
        for t in (17, torch.tensor(17), torch.tensor([17])):
            torch.testing.assert_close(model(x, t, ctx1), ref, rtol=1e-5, atol=1e-5)
        steps = torch.tensor([0, 17, 17, 50, 99, 3])
        per = model(x, steps, ctx1)
        assert (per[0] - ref[0]).abs().max() > 1e-3 and torch.allclose(per[1:3], ref[1:3], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    "dof,horizon,kind,spec",
    [
        (2, 16, "goal_joint_position", ModelSpec()),
        (7, 24, "goal_ee_pose", ModelSpec(unet_dim=32, unet_dim_mults=[1, 2, 4, 8], context_dim=128, context_layers=2)),
    ],
    ids=["2d", "panda"],
)
def test_channels_last_2d_inference_path_matches_the_1d_convolutions(dof, horizon, kind, spec):
    """The U-Net's CPU inference path (convolutions as channels-last 2-D ones) against its 1-D reference: the same
    outputs to float32 rounding (and bf16 autocast's), the 1-D path bitwise whenever autograd is on, and the cached
    4-D weights follow new weights (load_state_dict, an in-place update)."""
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    model = DiffusionModel(dof, horizon, kind, spec).eval()
    unet = model.unet
    x = torch.randn(5, horizon, dof, generator=g)
    ctx = {"q_start": torch.rand(5, dof, generator=g)}
    ctx.update(
        {"ee_pos": torch.rand(5, 3, generator=g), "ee_rot": torch.linalg.qr(torch.randn(5, 3, 3, generator=g)).Q}
        if kind == "goal_ee_pose"
        else {"q_goal": torch.rand(5, dof, generator=g)}
    )
    t = torch.tensor([0, 3, 10, 50, 99])

    def both():
        with torch.no_grad():
            unet.channels_last_2d = True
            fast = model(x, t, ctx)
            unet.channels_last_2d = False
            ref = model(x, t, ctx)
            unet.channels_last_2d = True
        return fast, ref

    fast, ref = both()
    assert ref.abs().mean() > 0.1
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        fast_b, ref_b = both()
    torch.testing.assert_close(fast_b.float(), ref.float(), rtol=0.1, atol=0.1)
    assert (fast_b.float() - ref).abs().mean() < 2 * (ref_b.float() - ref).abs().mean() + 1e-3
    # with autograd: the 1-D path, bitwise
    unet.channels_last_2d = False
    ref_grad = model(x, t, ctx)
    unet.channels_last_2d = True
    assert torch.equal(model(x, t, ctx), ref_grad)
    # new weights: in place, then by load_state_dict
    with torch.no_grad():
        for p in unet.parameters():
            p.mul_(1.1)
    fast, ref = both()
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)
    other = DiffusionModel(dof, horizon, kind, spec)
    model.load_state_dict(other.state_dict())
    fast2, ref2 = both()
    torch.testing.assert_close(fast2, ref2, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(fast2, fast)


def test_compiled_inference_matches_eager_follows_new_weights_and_compiles_once_per_shape():
    """``DiffusionModel(..., compiled=True)`` (TemporalUnet.compiled: torch.compile, frozen weights) against the eager
    network: the same outputs to float32 rounding; every diffusion step (given as an int or a tensor) runs the one
    graph of its shape; new weights (in place, load_state_dict) rebuild the graph instead of going stale; a copy of
    the module carries no compiled graph; with autograd on it refuses."""
    import copy

    from torch._dynamo.utils import counters

    torch.manual_seed(0)
    spec = ModelSpec(unet_dim=8, unet_dim_mults=[1, 2], context_dim=16, context_layers=1, time_emb_dim=8)
    model = DiffusionModel(2, 16, "goal_joint_position", spec).eval()
    g = torch.Generator().manual_seed(1)
    x = torch.randn(6, 16, 2, generator=g)
    ctx = {"q_start": torch.rand(1, 2, generator=g), "q_goal": torch.rand(1, 2, generator=g)}
    torch._dynamo.reset()
    counters.clear()
    with torch.no_grad():
        for t in (99, 37, torch.tensor(5), 0):
            torch.testing.assert_close(model(x, t, ctx, compiled=True), model(x, t, ctx), rtol=1e-5, atol=1e-5)
        # the context's embedding given in place of its fields (what a planner does): the same graph, the same output
        emb = model.embed_context(ctx)
        assert torch.equal(model(x, 37, emb, compiled=True), model(x, 37, ctx, compiled=True))
        assert counters["stats"]["unique_graphs"] == 1
        before = model(x, 10, ctx, compiled=True)
        for p in model.unet.parameters():
            p.mul_(1.1)
        after = model(x, 10, ctx, compiled=True)
        torch.testing.assert_close(after, model(x, 10, ctx), rtol=1e-5, atol=1e-5)
        assert not torch.allclose(before, after)
        model.load_state_dict(DiffusionModel(2, 16, "goal_joint_position", spec).state_dict())
        torch.testing.assert_close(model(x, 10, ctx, compiled=True), model(x, 10, ctx), rtol=1e-5, atol=1e-5)
        # a parameter replaced by another object (not updated in place)
        before = model(x, 10, ctx, compiled=True)
        conv1 = next(m for m in model.unet.modules() if isinstance(m, torch.nn.Conv1d))
        conv1.weight = torch.nn.Parameter(conv1.weight.detach() * 1.5)
        after = model(x, 10, ctx, compiled=True)
        torch.testing.assert_close(after, model(x, 10, ctx), rtol=1e-5, atol=1e-5)
        assert not torch.allclose(before, after)
    assert "_compiled" in model.unet.__dict__ and "_param_refs" in model.unet.__dict__
    assert not {"_compiled", "_param_refs"} & set(copy.deepcopy(model).unet.__dict__)
    with pytest.raises(RuntimeError, match="no_grad"):
        model(x, 10, ctx, compiled=True)


@pytest.mark.parametrize("autocast", [False, True])
def test_context_embedding_in_place_of_the_fields_is_the_same_network(autocast):
    """``DiffusionModel.forward`` given the context's embedding (``embed_context``, computed once per denoising
    process by the planners) returns exactly what it returns for the fields, with and without a goal head, in fp32
    and under bf16 autocast; the embedding is not the fields' values (the test would pass on an identity)."""
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(2)
    for kind, head, dof in (("goal_joint_position", 0, 2), ("goal_ee_pose", 8, 7)):
        spec = ModelSpec(unet_dim=8, unet_dim_mults=[1, 2], context_dim=16, context_layers=1, time_emb_dim=8)
        spec = dataclasses.replace(spec, goal_head_width=head)
        model = DiffusionModel(dof, 16, kind, spec).eval()
        x = torch.randn(5, 16, dof, generator=g)
        if kind == "goal_joint_position":
            ctx = {"q_start": torch.rand(1, dof, generator=g), "q_goal": torch.rand(1, dof, generator=g)}
        else:
            rot = torch.linalg.qr(torch.randn(1, 3, 3, generator=g)).Q
            ctx = {"q_start": torch.rand(1, dof, generator=g), "ee_pos": torch.rand(1, 3, generator=g), "ee_rot": rot}
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            emb = model.embed_context(ctx)
            assert emb.shape == (1, 16) and emb.dtype == (torch.bfloat16 if autocast else torch.float32)
            for t in (90, 3):
                assert torch.equal(model(x, t, emb), model(x, t, ctx))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_exponential_mish_is_mish(dtype):
    """The compiled network's Mish (one exponential) against torch's: values and gradients over the whole range,
    the switch to the identity included; no inf or NaN where e^x (e^x + 2) would overflow."""
    from mpd.models.unet import MISH_LINEAR_FROM, mish

    x = torch.cat([torch.linspace(-120, 120, 20001, dtype=dtype), torch.tensor([0.0, MISH_LINEAR_FROM], dtype=dtype)])
    x = torch.cat([x, torch.nextafter(x[-1:], x[-1:] + 1), torch.nextafter(x[-1:], x[-1:] - 1)]).requires_grad_(True)
    got, want = mish(x), torch.nn.functional.mish(x)
    eps = torch.finfo(dtype).eps
    torch.testing.assert_close(got, want, rtol=8 * eps, atol=8 * eps)
    (g_got,) = torch.autograd.grad(got.sum(), x)
    (g_want,) = torch.autograd.grad(want.sum(), x)
    assert torch.isfinite(g_got).all()
    torch.testing.assert_close(g_got, g_want, rtol=64 * eps, atol=64 * eps)


def test_min_start_goal_distance_trains_on_the_long_contexts_only(tmp_path):
    """The option's samples, against a loop over the contexts; the excluded samples never reach the weights (their
    paths shuffled among themselves: the same normalization, bit-identical weights; unfiltered, other weights)."""
    from mpd.models.train import model_identity, training_indices

    arrays = toy_arrays(n=24, n_val=4)
    ts = tiny_training(min_start_goal_distance=1.0)
    kept = [
        i for i in range(24)
        if arrays.split[i] == 0 and math.dist(arrays.context["q_goal"][i], arrays.context["q_start"][i]) >= 1.0
    ]  # fmt: skip
    assert 0 < len(kept) < 20 and training_indices(arrays, ts).tolist() == kept
    assert training_indices(arrays, tiny_training()).tolist() == list(range(20))
    assert model_identity("h", "diffusion", "bspline", {}, TINY, tiny_training(), 0) == model_identity(
        "h", "diffusion", "bspline", {}, TINY, tiny_training(min_start_goal_distance=0.0), 0
    )  # 0 is the paper: the identities of the models trained before the option stay
    assert model_identity("h", "diffusion", "bspline", {}, TINY, ts, 0) != model_identity(
        "h", "diffusion", "bspline", {}, TINY, tiny_training(), 0
    )
    dropped = [i for i in range(20) if i not in kept]
    shuffled = toy_arrays(n=24, n_val=4, dataset_hash="data1")
    shuffled.x[dropped] = arrays.x[dropped[::-1]]
    weights = {}
    for name, arr, spec in [("a", arrays, ts), ("b", shuffled, ts), ("a_all", arrays, tiny_training()),
                            ("b_all", shuffled, tiny_training())]:  # fmt: skip
        weights[name] = read_checkpoint(train_model(arr, "diffusion", TINY, spec, progress=False, cache=tmp_path))
    assert all(torch.equal(weights["a"]["weights"][k], weights["b"]["weights"][k]) for k in weights["a"]["weights"])
    assert any(not torch.equal(weights["a_all"]["weights"][k], weights["b_all"]["weights"][k])
               for k in weights["a_all"]["weights"])  # fmt: skip
    assert weights["a"]["training_spec"]["min_start_goal_distance"] == 1.0
    with pytest.raises(ValueError, match="min_start_goal_distance = 1.0: Toy has an end-effector goal"):
        train_model(toy_arrays(ee=True), "diffusion", TINY, ts, progress=False, cache=tmp_path)
    for d, why in [(9.0, "9.0: no training context of Toy"), (-1.0, "-1.0 is not allowed")]:
        with pytest.raises(ValueError, match=f"min_start_goal_distance = {why}"):
            train_model(arrays, "diffusion", TINY, tiny_training(min_start_goal_distance=d), cache=tmp_path)
