"""The planner interface: every registered planner returns the same structure; MPD without guidance is Dprior bit for
bit; guidance never moves a sample more than delta; bad input to `mpd plan` fails before any work.

Diffusion and CVAE planners run with small, randomly initialised networks here: the structure and the sampling
maths do not depend on the weights (sample quality is measured by the experiments, not by unit tests).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from mpd.planners import PLANNERS, Context, make_planner
from mpd.planners import mpd as mpd_module
from mpd.planners.conformance import random_model
from mpd.tasks import load_task
from mpd.tasks.spec import ModelSpec

SMALL = ModelSpec(unet_dim=8, unet_dim_mults=[1, 2], context_dim=8, context_layers=1, time_emb_dim=8)


def context_of(task) -> Context:
    # a fixed, collision-free start and goal of each task used here
    q = {
        "EnvSimple2D-RobotPointMass2D": ([-0.2, -0.9], [-0.2, 0.9]),
        "EnvPlanar4Link-RobotPlanar4Link": ([1.2, 0.3, 0.2, -0.3], [-1.6, 0.4, -0.3, 0.4]),
        "EnvSpheres3D-RobotPanda": (
            [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785],
            [0.5, 0.3, -0.4, -2.0, 0.2, 2.0, 0.5],
        ),
    }[task.name]
    qs, qg = (torch.tensor(v, dtype=torch.float32) for v in q)
    if task.ee_goal:
        p, r = task.robot.ee_pose(qg.double())
        return Context(qs, None, p.float(), r.float())
    return Context(qs, qg)


def build(name: str, task, **kw):
    kind = PLANNERS[name].model_kind
    model = random_model(task, kind) if kind else None
    return make_planner(name, task, model=model, device="cpu", **kw)


@pytest.mark.parametrize("task_name", ["EnvSimple2D-RobotPointMass2D", "EnvPlanar4Link-RobotPlanar4Link"])
@pytest.mark.parametrize("name", sorted(PLANNERS))
def test_every_planner_returns_the_same_structure(name, task_name):
    task = load_task(task_name)
    planner = build(name, task, extra_objects=True, overrides={"rrt_time_limit": 5.0})
    ctx = context_of(task)
    res = planner.plan(ctx, 6, seed=3, record_history=True)
    param = planner.param
    assert res.free.shape == (6, param.n_free, task.dof)
    assert res.control_points.shape == (6, param.n_params, task.dof)
    for x in (res.dense.q, res.dense.dq_ds, res.dense.ddq_ds2):
        assert x.shape == (6, param.n_points, task.dof) and torch.isfinite(x).all()
    assert torch.allclose(res.dense.q[:, 0], ctx.q_start.expand(6, -1), atol=1e-5)
    if ctx.q_goal is not None:
        assert torch.allclose(res.dense.q[:, -1], ctx.q_goal.expand(6, -1), atol=1e-5)
    assert res.timings["total"] > 0 and all(np.isfinite(v) for v in res.timings.values())
    assert res.history and all(h.free.shape == res.free.shape for h in res.history)
    if planner.uses_cost:
        assert res.timings["cost_gradient"] > 0
    again = build(name, task, extra_objects=True, overrides={"rrt_time_limit": 5.0}).plan(ctx, 6, seed=3)
    assert torch.equal(res.free, again.free), "same seed, same trajectories"


@pytest.mark.parametrize("sampler", ["ddim", "ddpm"])
def test_mpd_without_guidance_is_dprior_bit_for_bit(sampler):
    task = load_task("EnvSimple2D-RobotPointMass2D")
    model = random_model(task, "diffusion")
    ctx = context_of(task)
    ov = {"sampler": sampler}
    unguided = make_planner(
        "mpd", task, model=model, device="cpu", overrides={**ov, "guide_fraction": 0.0, "ddpm_guide_fraction": 0.0}
    )
    dprior = make_planner("dprior", task, model=model, device="cpu", overrides=ov)
    a, b = unguided.plan(ctx, 16, seed=7), dprior.plan(ctx, 16, seed=7)
    assert torch.equal(a.free, b.free)
    guided = make_planner("mpd", task, model=model, device="cpu", overrides=ov, extra_objects=True)
    assert not torch.equal(guided.plan(ctx, 16, seed=7).free, b.free)


@pytest.mark.parametrize("preset", ["official", "paper"])
def test_guidance_never_moves_a_sample_more_than_delta(monkeypatch, preset):
    task = load_task("EnvSimple2D-RobotPointMass2D")
    delta = 0.05
    planner = make_planner(
        "mpd",
        task,
        model=random_model(task, "diffusion"),
        device="cpu",
        extra_objects=True,
        preset=preset,
        overrides={"max_perturb": delta, "guide_lr": 5.0},
    )
    moves = []
    if preset == "official":
        orig = mpd_module.project

        def spy(x, anchor, max_perturb):
            out = orig(x, anchor, max_perturb)
            moves.append(float((out - anchor).abs().max()))
            return out

        monkeypatch.setattr(mpd_module, "project", spy)
    else:
        orig = mpd_module.optimize

        def spy(x0, grad_fn, steps, lr, max_perturb, grad_clip, callback=None):
            out = orig(x0, grad_fn, steps, lr, max_perturb, grad_clip, callback)
            moves.append(float((out - x0).abs().max()))
            return out

        monkeypatch.setattr(mpd_module, "optimize", spy)
    planner.plan(context_of(task), 32, seed=0)
    s = planner.settings
    assert len(moves) == (s.guided_steps(s.ddim_steps) * (s.n_inner_steps if preset == "official" else 1))
    assert max(moves) <= delta + 1e-6
    assert max(moves) > delta / 2, "with a large step size the guidance should reach the bound"


def test_presets_differ_where_the_paper_and_configs_differ():
    from mpd.planners import planner_settings

    task = load_task("EnvWarehouse-RobotPanda")
    off, pap = planner_settings(task, "official"), planner_settings(task, "paper")
    assert off.guided_steps(15) == 3 and pap.guided_steps(15) == 3  # Warehouse: fraction 0.2 -> ceil(3)
    assert planner_settings(load_task("EnvSpheres3D-RobotPanda")).guided_steps(15) == 5
    assert (off.eta, pap.eta) == (0.5, 0.0) and (off.grad_clip, pap.grad_clip) == (1.0, None)
    assert (off.cost_preset, pap.cost_preset) == ("official", "paper")
    with pytest.raises(ValueError, match="guide_rate"):
        planner_settings(task, "official", guide_rate=1.0)


def _plan_cli(*args):
    return subprocess.run([sys.executable, "-m", "mpd.cli", "plan", *args], capture_output=True, text=True)


@pytest.mark.parametrize(
    ("args", "expect"),
    [
        (["--planner", "mpdd"], "unknown planner 'mpdd'"),
        (
            ["--planner", "gp-cost", "--start", "0.1,0.2,0.3", "--goal", "0.5,0.5"],
            "has 3 values, the robot has 2 joints",
        ),
        (["--planner", "gp-cost", "--start", "1.5,0.0", "--goal", "0.5,0.5"], "joint 0 = 1.5 is outside its limits"),
        (["--planner", "gp-cost", "--start", "-0.37,-0.12", "--goal", "0.5,0.5"], "in collision with the environment"),
        (["--planner", "gp-cost", "--start", "-0.2,-0.9"], "give both a start and a goal"),
        (["--planner", "gp-cost", "--start", "nan,0", "--goal", "0.5,0.5"], "--start: entry 0 is nan (not a finite"),
        (["--planner", "mpd", "--model", "ffff"], "--model: no diffusion model with the bspline parametrization"),
    ],
)
def test_plan_cli_rejects_bad_input_before_any_work(tmp_path, args, expect):
    r = _plan_cli("--task", "EnvSimple2D-RobotPointMass2D", "--out", str(tmp_path / "o"), *args)
    assert r.returncode == 2, r.stderr
    assert expect in r.stderr and r.stderr.strip().count("\n") == 0
    assert not (tmp_path / "o").exists()


def test_plan_cli_writes_outputs(tmp_path):
    out = tmp_path / "gp"
    r = _plan_cli(
        "--task",
        "EnvSimple2D-RobotPointMass2D",
        "--planner",
        "gp-cost",
        "--n-samples",
        "8",
        "--start",
        "-0.2,-0.9",
        "--goal",
        "-0.2,0.9",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    import json

    doc = json.loads((out / "metrics.json").read_text())
    assert doc["planner"] == "gp-cost" and len(doc["contexts"]) == 1 and "total" in doc["contexts"][0]["timings"]
    assert (out / "trajectories.png").stat().st_size > 0 and (out / "trajectories.npz").exists()


def test_plan_cli_takes_the_named_models_parametrization(tmp_path):
    """`mpd plan --model <a waypoint prior's identity>` plans with waypoints without --parametrization; a
    contradicting --parametrization fails in one line naming --model."""
    import json

    from mpd.models.find import shipped_priors

    wp = shipped_priors("EnvSimple2D-RobotPointMass2D", "diffusion", "waypoints")[0]  # the default
    args = ["--task", "EnvSimple2D-RobotPointMass2D", "--planner", "dprior", "--model", wp["identity"][:8]]
    r = _plan_cli(*args, "--n-samples", "4", "--out", str(tmp_path / "wp"))
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "wp" / "metrics.json").read_text())
    assert doc["parametrization"] == "waypoints" and wp["identity"] in doc["model"]
    r = _plan_cli(*args, "--parametrization", "bspline", "--out", str(tmp_path / "b"))
    assert r.returncode == 2 and "--model: " in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr


def test_endpoint_gp_fit_and_posterior_match_scikit_learn():
    """The authors' GP prior: scikit-learn's GaussianProcessRegressor with 1 * RBF(l >= |qg - qs| / 2), fitted to the
    two end points (an independent implementation: L-BFGS-B with restarts) vs our closed-form fit."""
    sklearn_gp = pytest.importorskip("sklearn.gaussian_process")
    from sklearn.gaussian_process.kernels import RBF

    from mpd.planners.gp_cost import endpoint_gp_posterior, fit_endpoint_gp

    rng = np.random.default_rng(0)
    cases = [rng.uniform(-1, 1, (2, 2)), rng.uniform(-2.9, 2.9, (2, 7)), np.array([[0.8, 0.2], [0.9, 0.3]])]
    cases.append(np.array([[0.5, -0.5], [-0.5, 0.5]]))  # a.b < 0: the fit sits at the lower bound
    phases = np.linspace(0, 1, 18)[1:-1]
    for qs, qg in cases:
        lb = np.linalg.norm(qg - qs) / 2
        gpr = sklearn_gp.GaussianProcessRegressor(
            kernel=1 * RBF(length_scale=lb, length_scale_bounds=(lb, 1e4)), n_restarts_optimizer=10, random_state=0
        )
        gpr.fit(np.array([[0.0], [1.0]]), np.stack([qs, qg]))
        c_ref, l_ref = gpr.kernel_.k1.constant_value, gpr.kernel_.k2.length_scale
        c, ell = fit_endpoint_gp(qs, qg)
        assert ell == pytest.approx(l_ref, rel=2e-3) and c == pytest.approx(c_ref, rel=2e-3)
        # the posterior, with scikit-learn's fitted kernel vs ours
        mean, cov = endpoint_gp_posterior(qs, qg, phases, c_ref, l_ref)
        m_ref, cov_ref = gpr.predict(phases[:, None], return_cov=True)
        assert np.allclose(mean[0], m_ref, atol=1e-8)
        assert np.allclose(cov[0], cov_ref[..., 0] if cov_ref.ndim == 3 else cov_ref, atol=1e-8)


def test_gp_prior_samples_are_seeded_and_follow_the_posterior():
    """GPprior+Cost's prior: repeatable with a seed (the authors' is not), and over many samples the empirical mean
    of the raw free control points matches the GP posterior mean at linspace(0, 1, n_free + 2)[1:-1]."""
    from mpd.planners.base import Timer
    from mpd.planners.gp_cost import endpoint_gp_posterior, fit_endpoint_gp

    task = load_task("EnvSimple2D-RobotPointMass2D")
    planner = make_planner("gp-cost", task, device="cpu")
    ctx = context_of(task)
    draw = lambda seed: planner.sample_prior(  # noqa: E731
        ctx, 4000, torch.Generator().manual_seed(seed), Timer(torch.device("cpu"))
    )
    a, b = draw(1), draw(1)
    assert torch.equal(a, b) and not torch.equal(a, draw(2))
    raw = planner.normalizer.unnormalize(a.double(), clip=False).numpy()
    qs, qg = ctx.q_start.double().numpy(), ctx.q_goal.double().numpy()
    c, ell = fit_endpoint_gp(qs, qg)
    phases = np.linspace(0, 1, planner.param.n_free + 2)[1:-1]
    mean, cov = endpoint_gp_posterior(qs, qg, phases, c, ell)
    se = np.sqrt(np.diagonal(cov[0]))[:, None] / np.sqrt(len(raw))
    assert np.all(np.abs(raw.mean(0) - mean[0]) < 5 * se + 1e-9)
    assert np.allclose(raw.var(0), np.diagonal(cov[0])[:, None], rtol=0.15, atol=1e-9)


class _LinearEps(torch.nn.Module):
    """A stand-in denoiser with a known output, eps(x, t) = 0.3 x + 0.01 (t + 1), so that a whole guided DDIM run
    can be computed by hand; it has the attributes the planner reads from a DiffusionModel."""

    def __init__(self):
        super().__init__()
        from mpd.models.diffusion import get_schedule

        self.schedule = get_schedule(100)
        self.n_diffusion_steps = 100

    def forward(self, x, t, context):
        return 0.3 * x + 0.01 * (t + 1)


def test_official_guided_step_matches_a_hand_computation():
    """One DDIM run whose last steps are guided (official update) vs the update written out by hand: quadratic cost
    C(x) = 1/2 |x - a|^2 in normalized space (gradient x - a), M inner iterations without noise, each clipped to
    x_t +- delta, then sigma z added once, unclipped. Noise drawn from the same seeded generator in the same order
    (initial x, then one z per step into a level >= 1)."""
    from mpd.models.diffusion import get_schedule

    task = load_task("EnvSimple2D-RobotPointMass2D")
    model = random_model(task, "diffusion")
    model.network = _LinearEps()
    ov = {"ddim_variant": "paper", "ddim_steps": 4, "guide_fraction": 0.75, "eta": 0.5, "max_perturb": 0.05}
    planner = make_planner("mpd", task, model=model, device="cpu", overrides=ov)
    s = planner.settings
    shape = (3, planner.param.n_free, task.dof)
    target = torch.linspace(-0.5, 0.5, shape[1] * shape[2]).reshape(1, shape[1], shape[2])
    planner.cost_grad_fn = lambda ctx, timer: lambda x: x - target
    got = planner.sample(context_of(task), 3, torch.Generator().manual_seed(11), planner_timer(), None)

    abar = get_schedule(100).tables["alphas_cumprod"]
    grid = [0, 10, 40, 90]  # floor(linspace(0, sqrt(90), 4)^2), distinct: no bumping
    pairs = [(90, 40), (40, 10), (10, 0), (0, -1)]
    assert [int(v) for v in np.floor(np.linspace(0, np.sqrt(90), 4) ** 2)] == grid
    gen = torch.Generator().manual_seed(11)
    x = torch.randn(shape, generator=gen)
    n_guided = 3  # ceil(0.75 * 4)
    for i, (t, tn) in enumerate(pairs):
        a_t = float(abar[t])
        a_n = 1.0 if tn == -1 else float(abar[tn])
        sigma = 0.5 * np.sqrt((1 - a_n) / (1 - a_t) * (1 - a_t / a_n)) if tn >= 0 else 0.0
        eps = 0.3 * x + 0.01 * (t + 1)

        def mean_step(xk, e, a_t=a_t, a_n=a_n, tn=tn, sigma=sigma):
            x0 = ((xk - np.sqrt(1 - a_t) * e) / np.sqrt(a_t)).clamp(-1, 1)
            return x0 if tn == -1 else np.sqrt(a_n) * x0 + np.sqrt(1 - a_n - sigma**2) * e

        if i < len(pairs) - n_guided:
            x_new = mean_step(x, eps)
        else:
            xk = x
            for _ in range(4):
                e = 0.25 * eps + 1.0 * (xk - target).clamp(-1, 1)
                xk = x + (mean_step(xk, e) - x).clamp(-0.05, 0.05)
            x_new = xk
        if tn >= 1 and sigma > 0:
            x_new = x_new + sigma * torch.randn(shape, generator=gen)
        x = x_new
    assert torch.allclose(got, x, atol=1e-6)
    assert s.guided_steps(4) == n_guided


def planner_timer():
    from mpd.planners.base import Timer

    return Timer(torch.device("cpu"))


def test_bf16_network_precision_denoises_like_fp32():
    """``planner.network_precision``: bf16 autocast of the denoising network. With the shipped EnvSimple2D prior, one
    denoising step's output (eps) is within 3 % (relative norm) of float32's, the samples of a whole Dprior plan stay
    close (mean distance well below the samples' own spread), the precision is recorded in the plan's info, and
    ``auto`` picks bf16 exactly where the CPU has native bf16 (AVX512_BF16 / AMX flags)."""
    from mpd.device import BF16_CPU_FLAGS, cpu_flags, network_precision
    from mpd.models.checkpoint import load_model
    from mpd.models.shipped import BUNDLED, MODELS

    task = load_task("EnvSimple2D-RobotPointMass2D")
    model = load_model(next((BUNDLED / MODELS / task.name).glob("diffusion-bspline-*.pt")))
    ctx = context_of(task)
    cond = model.normalize_context({"q_start": ctx.q_start, "q_goal": ctx.q_goal})
    x = torch.randn(100, model.horizon, task.dof, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        e32 = model.network(x, 20, cond)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            e16 = model.network(x, 20, cond).float()
    rel = float((e16 - e32).norm() / e32.norm())
    assert 0 < rel < 0.03
    plans = {}
    for precision in ("fp32", "bf16"):
        p = make_planner("dprior", task, model=model, device="cpu", overrides={"network_precision": precision})
        plans[precision] = res = p.plan(ctx, 100, seed=3)
        assert res.info["network_precision"] == precision
    a, b = plans["fp32"].free, plans["bf16"].free
    spread = (a - a.mean(0)).norm(dim=(1, 2)).mean()
    assert 0 < float((a - b).norm(dim=(1, 2)).mean()) < 0.1 * float(spread)
    assert network_precision("auto", "cpu") == ("bf16" if cpu_flags() & set(BF16_CPU_FLAGS) else "fp32")
    with pytest.raises(ValueError, match="network_precision"):
        network_precision("fp16", "cpu")


def test_compiled_network_plans_like_the_eager_one():
    """``planner.network_compile``: with the shipped EnvSimple2D prior's U-Net compiled (torch.compile, frozen
    weights) Dprior gives the eager plan's samples to float32 rounding (same random stream), and says so in its
    info. MPD too, but for the odd sample: the nearest-node SDF gradient jumps where the nearest node changes, so a
    rounding-sized difference can switch a guidance step's gradient, which then moves that sample by up to a clipped
    guidance step."""
    from mpd.models.checkpoint import load_model
    from mpd.models.shipped import BUNDLED, MODELS

    task = load_task("EnvSimple2D-RobotPointMass2D")
    model = load_model(next((BUNDLED / MODELS / task.name).glob("diffusion-bspline-*.pt")))
    ctx = context_of(task)
    for method in ("dprior", "mpd"):
        plans = {}
        for compiled in (False, True):
            p = make_planner(method, task, model=model, device="cpu", overrides={"network_compile": compiled})
            plans[compiled] = res = p.plan(ctx, 20, seed=3)
            assert res.info["network_compiled"] is compiled
        assert plans[True].free.std() > 0.1
        if method == "dprior":
            torch.testing.assert_close(plans[True].free, plans[False].free, rtol=1e-5, atol=1e-5)
            continue
        per_sample = (plans[True].free - plans[False].free).abs().amax(dim=(1, 2))
        assert float((per_sample < 1e-5).float().mean()) >= 0.9, per_sample
        half_range = float((p.normalizer.hi - p.normalizer.lo).max()) / 2
        assert float(per_sample.max()) < p.settings.max_perturb * half_range


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("task_name", ["EnvSimple2D-RobotPointMass2D", "EnvSpheres3D-RobotPanda"])
@pytest.mark.parametrize("method", ["mpd", "dprior", "cvae-cost"])
def test_cuda_plan_with_a_model_loaded_on_the_cpu(task_name, method):
    """A planner on a GPU given a model loaded on the CPU plans on the GPU with a copy of it (the caller's model
    stays on the CPU), and its samples have the CPU plan's shape and are finite (an H200 run of 2026-12-04 found
    the network left on the CPU)."""
    task = load_task(task_name)
    kind = "cvae" if method.startswith("cvae") else "diffusion"
    model = random_model(task, kind)
    planner = make_planner(method, task, model=model, device="cuda")
    assert next(planner.model.network.parameters()).is_cuda
    res = planner.plan(context_of(task), 8, seed=0)
    ref = make_planner(method, task, model=model, device="cpu").plan(context_of(task), 8, seed=0)
    assert next(model.network.parameters()).device.type == "cpu"
    assert res.free.shape == ref.free.shape and torch.isfinite(torch.as_tensor(res.free)).all()


def test_cli_names_a_missing_run_in_one_line(tmp_path):
    env = {**__import__("os").environ, "MPD_RUNS": str(tmp_path)}
    r = subprocess.run(
        [sys.executable, "-m", "mpd.cli", "runs", "compare", "nosuchrun", "other"],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 2 and r.stderr.strip() == f"error: no run found for nosuchrun in {tmp_path}"


def test_the_fast_path_is_the_default_only_where_it_can_compile(monkeypatch, tmp_path):
    """MPD_COMPILE=0 turns the default off, and so does a CPU without a C++ compiler on the PATH (inductor needs one):
    a user without g++ gets the eager network, not a compile error."""
    import shutil

    from mpd.device import can_compile
    from mpd.planners.settings import fast_enabled

    monkeypatch.delenv("MPD_COMPILE", raising=False)
    monkeypatch.delenv("CXX", raising=False)
    has_cxx = any(shutil.which(n) for n in ("g++", "c++", "clang++"))
    assert can_compile("cpu") == has_cxx and fast_enabled("cpu") == has_cxx and fast_enabled()
    monkeypatch.setenv("MPD_COMPILE", "0")
    assert not fast_enabled() and not fast_enabled("cpu")
    monkeypatch.delenv("MPD_COMPILE")
    monkeypatch.setenv("PATH", str(tmp_path))  # an empty folder: no compiler anywhere
    assert not can_compile("cpu") and not fast_enabled("cpu")
    (tmp_path / "my-cxx").write_text("#!/bin/sh\n")
    (tmp_path / "my-cxx").chmod(0o755)
    monkeypatch.setenv("CXX", "my-cxx")
    assert can_compile("cpu") and fast_enabled("cpu")
