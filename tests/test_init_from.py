"""A training started from another checkpoint's EMA weights (``train_model(init_from=...)``, ``mpd train
--init-from``): the weights and the EMA it starts from, a fresh optimizer, an identity of its own that names where
it came from, exact resume, and clear errors for a checkpoint of another network or dataset."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from mpd.models.checkpoint import read_checkpoint
from mpd.models.train import train_model
from mpd.schema import ConfigError
from tests.test_models import TINY, tiny_training, toy_arrays

pytestmark = pytest.mark.usefixtures("one_thread")


def _train(tmp_path, name, spec, arrays=None, model_spec=TINY, **kw):
    return train_model(
        arrays or toy_arrays(n=32, n_val=4), "diffusion", model_spec, spec, seed=1, device="cpu", progress=False,
        cache=tmp_path / name, compile_step=False, **kw,
    )  # fmt: skip


def test_a_continued_training_starts_from_the_ema_weights_with_its_own_identity(tmp_path):
    first = _train(tmp_path, "a", tiny_training(steps=30))
    ck_a = read_checkpoint(first)
    # at learning rate 0 AdamW leaves the weights where they start: the first model's EMA, in both weights and EMA
    still = read_checkpoint(_train(tmp_path, "b", tiny_training(steps=5, lr=0.0), init_from=first))
    for key in ("weights", "ema_weights"):
        assert all(torch.equal(still[key][k], ck_a["ema_weights"][k]) for k in ck_a["ema_weights"])
    assert still["init_from"]["identity"] == ck_a["identity"] and still["init_from"]["step"] == 30
    fresh = read_checkpoint(_train(tmp_path, "c", tiny_training(steps=5, lr=0.0)))
    assert fresh["identity"] != still["identity"] and "init_from" not in fresh
    assert not all(torch.equal(fresh["weights"][k], still["weights"][k]) for k in fresh["weights"])
    # a continued training resumes exactly: stopped at step 7 and resumed = run through
    spec = tiny_training(steps=20)
    whole = read_checkpoint(_train(tmp_path, "d", spec, init_from=first))
    part = _train(tmp_path, "e", spec, init_from=first, stop_after=7)
    ck_part = read_checkpoint(part)
    assert ck_part["step"] == 7
    resumed = read_checkpoint(_train(tmp_path, "e", spec, init_from=first))
    assert whole["identity"] == resumed["identity"] == ck_part["identity"]
    assert all(torch.equal(whole["ema_weights"][k], resumed["ema_weights"][k]) for k in whole["ema_weights"])
    # and it trains on from there: the weights moved, the loss lower than the fresh network's first
    assert not all(torch.equal(whole["weights"][k], ck_a["ema_weights"][k]) for k in whole["weights"])
    assert whole["history"][0]["train_loss"] < ck_a["history"][0]["train_loss"]


def test_init_from_a_checkpoint_of_another_network_or_dataset_is_a_clear_error(tmp_path):
    first = _train(tmp_path, "a", tiny_training(steps=10))
    wider = dataclasses.replace(TINY, unet_dim=8)
    with pytest.raises(ConfigError, match="model_spec"):
        _train(tmp_path, "b", tiny_training(steps=5), model_spec=wider, init_from=first)
    other = toy_arrays(n=32, n_val=4, dataset_hash="data1")
    with pytest.raises(ConfigError, match="dataset_hash"):
        _train(tmp_path, "c", tiny_training(steps=5), arrays=other, init_from=first)
