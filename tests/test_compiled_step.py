"""The CPU training step with the loss compiled by torch.compile (mpd.models.compiled_step): the same training as the
eager loop up to float rounding, deterministic itself, resumable across modes in both directions, recorded, and
chosen by default only where it pays (long runs; never for the retraining of an eagerly trained shipped prior).

Tolerances. The compiled step draws the same batches, steps and noise from the same generator and runs the same
clipping, fused AdamW and EMA; only the loss's forward and backward are fused kernels that round differently
(GroupNorm's reductions, Mish written with one exponential, sums in another order). In fp32 each step's gradient then
differs from the eager one by a few ulp, and AdamW maps a relative gradient change to about the same relative change of
its update (lr x m / sqrt(v)): after N steps the weights differ by far less than lr (1e-3) -- but AdamW's first
step is close to lr x sign(g): an element whose gradient is at the scale of its epsilon (1e-8) moves by a rounding-
dependent fraction of lr (measured: 6.7e-5 on one element at step 0, unchanged after 30 steps, relative norm of the
whole difference 3e-6). Bounds: max 0.5 lr per element and 1e-5 relative norm, which a wrong draw, a missing EMA
update or a wrong learning rate (each a full step, ~lr on nearly every element) would exceed. Under bf16 autocast
the fused kernels keep intermediates in fp32 where eager rounds them to bf16 (8 bits of mantissa), so the two runs
differ by bf16 rounding: the bound is twice the difference bf16 autocast itself makes (eager bf16 against eager fp32,
same draws).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from mpd.models import compiled_step
from mpd.models.checkpoint import read_checkpoint
from mpd.models.train import list_models, train_model
from tests.test_models import TINY, tiny_training, toy_arrays

pytestmark = [
    pytest.mark.skipif(not compiled_step.cxx_available(), reason="inductor needs a C++ compiler"),
    pytest.mark.usefixtures("one_thread"),
]

LR = 1e-3  # tiny_training's
FP32 = {"max_abs": 0.5 * LR, "rel": 1e-5}


def _state(path):
    ck = read_checkpoint(path)
    return ck, {k: v.float() for k, v in ck["weights"].items()}, {k: v.float() for k, v in ck["ema_weights"].items()}


def _max_diff(a: dict, b: dict) -> float:
    return max((a[k] - b[k]).abs().max().item() for k in a)


def _rel_norm(a: dict, b: dict) -> float:
    """||a - b|| / ||b|| over all tensors together."""
    diff = sum(float((a[k] - b[k]).double().pow(2).sum()) for k in a)
    return (diff / sum(float(b[k].double().pow(2).sum()) for k in b)) ** 0.5


def _close(a: dict, b: dict, max_abs: float, rel: float, what: str) -> None:
    d, r = _max_diff(a, b), _rel_norm(a, b)
    print(f"{what}: max |difference| {d:.3g}, relative norm {r:.3g}")
    assert d <= max_abs and r <= rel, what


def _run(tmp_path, name, spec, **kw):
    return train_model(
        toy_arrays(n=64, n_val=8), "diffusion", TINY, spec, seed=3, device="cpu", progress=False,
        cache=tmp_path / name, **kw,
    )  # fmt: skip


def test_compiled_training_equals_eager_in_fp32_and_repeats_itself(tmp_path):
    spec = tiny_training(steps=30, ema_start=10, ema_every=2, checkpoint_every=1000, lr_schedule="cosine")
    ck_c, w_c, e_c = _state(_run(tmp_path, "c", spec, compile_step=True))
    _, w_c2, e_c2 = _state(_run(tmp_path, "c2", spec, compile_step=True))
    ck_e, w_e, e_e = _state(_run(tmp_path, "e", spec, compile_step=False))
    assert ck_c["execution"] == [[0, "compiled"]] and "execution" not in ck_e
    assert ck_c["identity"] == ck_e["identity"]
    assert all(torch.equal(w_c[k], w_c2[k]) for k in w_c) and all(torch.equal(e_c[k], e_c2[k]) for k in e_c)
    _close(w_c, w_e, **FP32, what="fp32, 30 steps, weights")
    _close(e_c, e_e, **FP32, what="fp32, 30 steps, EMA")
    # the losses logged on the way agree too
    for a, b in zip(ck_c["history"], ck_e["history"]):
        assert a["train_loss"] == pytest.approx(b["train_loss"], rel=1e-4)
    meta = list_models("Toy", cache=tmp_path / "c")[0]
    assert meta["execution"] == [[0, "compiled"]]


def test_compiled_training_is_near_eager_under_bf16_autocast(tmp_path, monkeypatch):
    """Within bf16 rounding of the eager bf16 run: no further from it than twice what bf16 autocast itself changes
    (the eager bf16 run against the eager fp32 run of the same draws; measured: all three runs about equally apart,
    3-4e-3 relative after 12 steps, since each rounds to bf16 at other points)."""
    monkeypatch.setenv("MPD_BF16", "emulate")  # bf16 autocast on any CPU (slow without AVX512_BF16; a tiny net)
    spec = tiny_training(steps=12, ema_start=4, ema_every=2, checkpoint_every=1000, precision="bf16")
    _, w_c, e_c = _state(_run(tmp_path, "c", spec, compile_step=True))
    _, w_e, e_e = _state(_run(tmp_path, "e", spec, compile_step=False))
    _, w_32, e_32 = _state(_run(tmp_path, "e32", dataclasses.replace(spec, precision="fp32"), compile_step=False))
    bf16_effect = _rel_norm(w_e, w_32)
    print(f"bf16 autocast vs fp32 (eager), 12 steps: relative norm {bf16_effect:.3g}")
    _close(w_c, w_e, max_abs=10 * LR, rel=2 * bf16_effect, what="bf16, 12 steps, weights")
    _close(e_c, e_e, max_abs=10 * LR, rel=2 * _rel_norm(e_e, e_32), what="bf16, 12 steps, EMA")


@pytest.mark.parametrize(
    "first,then", [(False, True), (True, False)], ids=["eager-then-compiled", "compiled-then-eager"]
)
def test_a_training_resumes_across_modes(tmp_path, first, then):
    """A ``last.pt`` written by one mode (the same keys) is resumed by the other: the run ends where an uninterrupted
    eager run ends (to the fp32 tolerance), and the checkpoint says from which step each mode ran."""
    spec = tiny_training(steps=30, ema_start=10, ema_every=2, checkpoint_every=1000)
    partial = _run(tmp_path, "r", spec, compile_step=first, stop_after=13)
    ck_p = read_checkpoint(partial)
    assert ck_p["step"] == 13
    keys = set(ck_p)
    ck_r, w_r, e_r = _state(_run(tmp_path, "r", spec, compile_step=then))
    _, w_e, e_e = _state(_run(tmp_path, "e", spec, compile_step=False))
    mode = {False: "eager", True: "compiled"}
    assert ck_r["step"] == 30 and ck_r["execution"] == [[0, mode[first]], [13, mode[then]]]
    assert keys - {"execution"} <= set(ck_r) | {"optimizer", "rng", "running_loss", "running_n"}
    _close(w_r, w_e, **FP32, what=f"resumed {mode[first]} -> {mode[then]}, weights")
    _close(e_r, e_e, **FP32, what=f"resumed {mode[first]} -> {mode[then]}, EMA")


def test_the_compiled_step_is_the_default_for_long_cpu_runs_only(monkeypatch):
    cpu = torch.device("cpu")
    monkeypatch.delenv(compiled_step.ENV, raising=False)
    assert compiled_step.compile_by_default("diffusion", cpu, compiled_step.MIN_STEPS)
    assert not compiled_step.compile_by_default("diffusion", cpu, compiled_step.MIN_STEPS - 1)
    assert not compiled_step.compile_by_default("cvae", cpu, 10**6)
    assert not compiled_step.compile_by_default("diffusion", torch.device("meta"), 10**6)
    monkeypatch.setenv(compiled_step.ENV, "1")
    assert compiled_step.compile_by_default("diffusion", cpu, 10)
    monkeypatch.setenv(compiled_step.ENV, "0")
    assert not compiled_step.compile_by_default("diffusion", cpu, 10**6)


def test_compile_step_is_refused_where_it_does_not_apply(tmp_path):
    with pytest.raises(ValueError, match="compile_step=True"):
        train_model(toy_arrays(), "cvae", TINY, tiny_training(), device="cpu", cache=tmp_path, compile_step=True)


def test_retraining_an_eagerly_shipped_prior_stays_eager(tmp_path, monkeypatch):
    """``shipped=False`` retrains a shipped prior to reproduce it bit for bit: with its lock saying it was trained
    eagerly, the default stays eager even where the compiled step would be chosen (MPD_TRAIN_COMPILE=1)."""
    from mpd.models import shipped

    monkeypatch.setenv("MPD_PRIORS", str(tmp_path / "priors"))
    monkeypatch.setenv(compiled_step.ENV, "0")
    arrays, spec = toy_arrays(n_val=4), tiny_training(steps=10)
    trained = train_model(arrays, "diffusion", TINY, spec, seed=4, progress=False, cache=tmp_path / "a")
    shipped.ship(trained, tmp_path / "priors")
    monkeypatch.setenv(compiled_step.ENV, "1")
    again = train_model(arrays, "diffusion", TINY, spec, seed=4, progress=False, cache=tmp_path / "b", shipped=False)
    a, b = read_checkpoint(trained)["ema_weights"], read_checkpoint(again)["ema_weights"]
    assert "execution" not in read_checkpoint(again)
    assert all(torch.equal(a[k], b[k]) for k in a)
