"""Data-parallel training (mpd.models.data_parallel): real spawned processes, gradients averaged in shared memory.

Against the one-process training as the reference: the ranks draw the one-process batches, steps and noise and
average their slices' gradients, so a 2-rank run is the same training up to float rounding (the loss's means over
64 + 64 rows instead of 128, the gradients' sums in another order). Bounds as in tests/test_compiled_step.py (the
same kind of rounding difference): max 0.5 lr per element and 1e-5 relative norm after 30 steps, which a rank
drawing its own batch, a missing average (gradients 2x or 1/2) or an unsynchronized rank would exceed by far. The
2-rank run itself repeats bit for bit, resumes exactly, and interoperates with one-process checkpoints.
"""

from __future__ import annotations

import dataclasses
import shutil
import signal

import pytest
import torch

from mpd.models import data_parallel as dp
from mpd.models import step as step_module
from mpd.models.checkpoint import read_checkpoint
from mpd.models.train import train_model
from tests.test_compiled_step import FP32, _close, _state
from tests.test_models import TINY, tiny_training, toy_arrays

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.slow]


def _run(tmp_path, name, spec, **kw):
    return train_model(
        toy_arrays(n=64, n_val=8), "diffusion", TINY, spec, seed=3, device="cpu", progress=False,
        cache=tmp_path / name, compile_step=False, **kw,
    )  # fmt: skip


SPEC = dict(steps=30, ema_start=10, ema_every=2, checkpoint_every=1000)


def test_two_ranks_train_what_one_process_trains_and_repeat_themselves(tmp_path):
    spec = tiny_training(**SPEC)
    ck_2, w_2, e_2 = _state(_run(tmp_path, "dp", spec, data_parallel=2))
    _, w_2b, e_2b = _state(_run(tmp_path, "dp-again", spec, data_parallel=2))
    ck_1, w_1, e_1 = _state(_run(tmp_path, "one", spec))
    assert ck_2["identity"] == ck_1["identity"]
    assert ck_2["execution"] == [[0, "eager/2"]] and "execution" not in ck_1
    assert all(torch.equal(w_2[k], w_2b[k]) for k in w_2) and all(torch.equal(e_2[k], e_2b[k]) for k in e_2)
    _close(w_2, w_1, **FP32, what="2 ranks vs 1, 30 steps, weights")
    _close(e_2, e_1, **FP32, what="2 ranks vs 1, 30 steps, EMA")
    # the logged training loss is the whole batch's (the ranks' mean), the validation loss rank 0's
    for a, b in zip(ck_2["history"], ck_1["history"]):
        assert a["train_loss"] == pytest.approx(b["train_loss"], rel=1e-5)
        assert a["val_loss"] == pytest.approx(b["val_loss"], rel=1e-5)


def test_a_rank_on_the_wrong_rows_is_told_apart(tmp_path, monkeypatch):
    """The bounds above catch a wrong slice: rank 0 taking rank 1's rows (the patch acts in this process only, the
    spawned rank is unpatched) trains on half of each batch twice and ends far off."""
    spec = tiny_training(**SPEC)
    _, w_1, _ = _state(_run(tmp_path, "one", spec))
    take = dp.Shard.take

    def rank_1_rows(self, *tensors):
        self.rows = slice(self.rows.stop, 2 * self.rows.stop)
        return take(self, *tensors)

    monkeypatch.setattr(dp.Shard, "take", rank_1_rows)
    _, w_bad, _ = _state(_run(tmp_path, "bad", spec, data_parallel=2))
    with pytest.raises(AssertionError):
        _close(w_bad, w_1, **FP32, what="rank 0 on rank 1's rows")


def test_one_process_and_two_ranks_resume_each_other_exactly(tmp_path):
    spec = tiny_training(**SPEC)
    partial = _run(tmp_path, "r", spec, stop_after=13)
    assert read_checkpoint(partial)["step"] == 13
    ck_r, w_r, e_r = _state(_run(tmp_path, "r", spec, data_parallel=2))
    assert ck_r["execution"] == [[0, "eager"], [13, "eager/2"]]
    # 2 ranks to 13 steps, then 2 ranks again: bit for bit the uninterrupted 2-rank run
    copy = tmp_path / "step-13.pt"
    shutil.copy(_run(tmp_path, "s", spec, stop_after=13, data_parallel=2), copy)
    # the 13-step budget made from that copy is that state, with the modes that made it (the call adds no step)
    budget = read_checkpoint(_run(tmp_path, "t", dataclasses.replace(spec, steps=13), start_from=copy))
    assert budget["step"] == 13 and budget["execution"] == [[0, "eager/2"]]
    _, w_s, e_s = _state(_run(tmp_path, "s", spec, data_parallel=2))
    _, w_2, e_2 = _state(_run(tmp_path, "dp", spec, data_parallel=2))
    assert all(torch.equal(w_s[k], w_2[k]) for k in w_2) and all(torch.equal(e_s[k], e_2[k]) for k in e_2)
    _, w_1, e_1 = _state(_run(tmp_path, "one", spec))
    _close(w_r, w_1, **FP32, what="1 process to 13, then 2 ranks, weights")


def test_ctrl_c_to_rank_0_stops_both_ranks_after_the_same_step_and_resumes_exactly(tmp_path, monkeypatch):
    """SIGINT reaches rank 0 only (as ``kill -INT <pid>``): both ranks stop after step 10, rank 0 saves ``last.pt``,
    the spawned rank exits cleanly, and the 2-rank resume ends bit for bit where the uninterrupted 2-rank run ends."""
    spec = tiny_training(**{**SPEC, "steps": 20, "val_every": 1000})
    _, w_ref, e_ref = _state(_run(tmp_path, "ref", spec, data_parallel=2))
    original, calls = step_module.apply_ema, []

    def ema_then_ctrl_c(ema_params, params, w):
        original(ema_params, params, w)
        calls.append(w)
        if len(calls) == 10:  # step 10 (0-based 9), in this process only
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(step_module, "apply_ema", ema_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt, match="step 10"):
        _run(tmp_path, "b", spec, data_parallel=2)
    monkeypatch.setattr(step_module, "apply_ema", original)
    last = next((tmp_path / "b").rglob("last.pt"))
    assert read_checkpoint(last)["step"] == 10
    _, w_b, e_b = _state(_run(tmp_path, "b", spec, data_parallel=2))
    assert all(torch.equal(w_b[k], w_ref[k]) for k in w_ref) and all(torch.equal(e_b[k], e_ref[k]) for k in e_ref)


def test_data_parallel_is_refused_where_it_does_not_apply(tmp_path):
    with pytest.raises(ValueError, match="not a multiple"):
        _run(tmp_path, "odd", tiny_training(batch_size=33), data_parallel=2)
    with pytest.raises(ValueError, match="only a diffusion training"):
        train_model(toy_arrays(), "cvae", TINY, tiny_training(), device="cpu", cache=tmp_path, data_parallel=2)
    with pytest.raises(ValueError, match="at least 1"):
        _run(tmp_path, "zero", tiny_training(), data_parallel=0)
