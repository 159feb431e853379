"""mpd.device.resolve: the one decision of the arithmetic a network runs in on a device, for training and planning."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import pytest
import torch

import mpd.device
from mpd.device import Arithmetic, resolve, training_request
from mpd.planners.mpd import MPD
from mpd.planners.settings import PlannerSettings


@pytest.fixture
def no_native_bf16(monkeypatch):
    monkeypatch.delenv("MPD_BF16", raising=False)
    monkeypatch.setattr(mpd.device, "native_bf16", lambda device: False)


def test_auto_is_fp32_on_a_cpu_without_native_bf16_and_an_explicit_request_is_kept(no_native_bf16):
    auto = resolve("cpu")
    assert (auto.requested, auto.dtype, auto.bf16, auto.native_bf16) == ("auto", "fp32", False, False)
    assert resolve("cpu", "fp32").dtype == "fp32"
    assert resolve("cpu", "bf16").dtype == "bf16"  # asked for: emulated
    assert auto.record() == {"arithmetic": "fp32"}
    with pytest.raises(ValueError, match="network_precision must be auto, fp32 or bf16"):
        resolve("cpu", "fp16", name="network_precision")
    with pytest.raises(dataclasses.FrozenInstanceError):
        auto.dtype = "bf16"


def test_auto_is_bf16_where_native_or_emulation_is_asked_for(no_native_bf16, monkeypatch):
    monkeypatch.setenv("MPD_BF16", "emulate")
    assert resolve("cpu").dtype == "bf16"
    assert resolve("cpu", "fp32").dtype == "fp32"
    monkeypatch.delenv("MPD_BF16")
    monkeypatch.setattr(mpd.device, "native_bf16", lambda device: True)
    native = resolve("cpu")
    assert native.dtype == "bf16" and native.native_bf16 and native.record() == {"arithmetic": "bf16"}


def test_autocast_runs_the_decided_arithmetic(no_native_bf16):
    a, b = torch.randn(4, 8), torch.randn(8, 3)
    with resolve("cpu", "fp32").autocast():
        assert (a @ b).dtype == torch.float32
    for cache in (True, False):
        with resolve("cpu", "bf16").autocast(cache_enabled=cache):
            assert (a @ b).dtype == torch.bfloat16


def test_cuda_graph_only_on_cuda_unless_turned_off(no_native_bf16, monkeypatch):
    monkeypatch.delenv("MPD_CUDA_GRAPH", raising=False)
    assert not resolve("cpu").cuda_graph
    assert resolve(torch.device("cuda")).cuda_graph == hasattr(torch.cuda.CUDAGraph, "register_generator_state")
    monkeypatch.setenv("MPD_CUDA_GRAPH", "0")
    assert not resolve(torch.device("cuda")).cuda_graph


@pytest.mark.parametrize("emulate", [False, True])
def test_one_decision_drives_training_and_planning(tmp_path, no_native_bf16, monkeypatch, emulate):
    """A training's bf16 precision and a planner's auto network precision are the same request: the same object,
    recorded by the trained model's meta (``arithmetic``) as the planner records it (``network_precision``)."""
    from mpd.models.train import train_model
    from tests.test_models import TINY, tiny_training, toy_arrays

    if emulate:
        monkeypatch.setenv("MPD_BF16", "emulate")
    expected = "bf16" if emulate else "fp32"
    training = resolve("cpu", training_request("bf16"))
    planner = SimpleNamespace(device=torch.device("cpu"), settings=PlannerSettings(network_precision="auto"))
    planning = MPD.arithmetic.fget(planner)
    assert isinstance(planning, Arithmetic) and planning == training and planning.dtype == expected
    assert mpd.device.network_precision("auto", "cpu") == mpd.device.training_arithmetic("bf16", "cpu") == expected
    ts = tiny_training(steps=2, precision="bf16")
    path = train_model(toy_arrays(), "diffusion", TINY, ts, progress=False, cache=tmp_path, shipped=False)
    assert json.loads((path.parent / "meta.json").read_text())["arithmetic"] == expected
