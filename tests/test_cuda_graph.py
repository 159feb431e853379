"""The training step captured in a CUDA graph (mpd.models.cuda_graph): its EMA rule against the eager loop's, its
refusal where it does not apply, and on a GPU the captured run against the eager one."""

from __future__ import annotations

import pytest
import torch

from mpd.models import train as train_module
from mpd.models.checkpoint import read_checkpoint
from mpd.models.cuda_graph import ema_weight, graph_supported
from mpd.models.step import apply_ema
from mpd.models.train import train_model
from tests.test_models import TINY, tiny_training, toy_arrays

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.parametrize("ema_every,ema_start", [(1, 0), (1, 7), (5, 20), (3, 4)])
def test_ema_weight_is_the_eager_loops_rule_as_one_lerp(ema_every, ema_start):
    """Replaying the lerp weights on tensors gives the eager loop's EMA (copies before ema_start, decay on EMA steps,
    nothing between), step for step; so does apply_ema with the weight as a float (the eager and compiled steps) and
    as a tensor (the captured step)."""
    ts = tiny_training(ema_every=ema_every, ema_start=ema_start, ema_decay=0.9)
    g = torch.Generator().manual_seed(0)
    w = torch.randn(50, generator=g)
    ema_eager, ema_lerp, ema_float, ema_tensor = w.clone(), w.clone(), w.clone(), w.clone()
    net = w.clone()
    for step in range(30):
        net = net + torch.randn(50, generator=g)
        done = step + 1
        if done % ts.ema_every == 0:
            if done < ts.ema_start:
                ema_eager.copy_(net)
            else:
                ema_eager.lerp_(net, 1.0 - ts.ema_decay)
        ema_lerp.lerp_(net, torch.tensor(ema_weight(ts, step)))
        apply_ema([ema_float], [net], ema_weight(ts, step))
        apply_ema([ema_tensor], [net], torch.tensor(ema_weight(ts, step)))
        for other in (ema_lerp, ema_float, ema_tensor):
            assert torch.equal(ema_eager, other), step


def test_capture_is_refused_where_it_does_not_apply(tmp_path, monkeypatch):
    arrays = toy_arrays()
    with pytest.raises(ValueError, match="cuda_graph=True"):
        train_model(arrays, "diffusion", TINY, tiny_training(), device="cpu", cache=tmp_path, cuda_graph=True)
    with pytest.raises(ValueError, match="cuda_graph=True"):
        train_model(arrays, "cvae", TINY, tiny_training(), device="cpu", cache=tmp_path, cuda_graph=True)
    assert not graph_supported("diffusion", torch.device("cpu"))
    assert not graph_supported("cvae", torch.device("cuda"))
    monkeypatch.setenv("MPD_CUDA_GRAPH", "0")
    assert not graph_supported("diffusion", torch.device("cuda"))


def _weights(path):
    ck = read_checkpoint(path)
    return ck, {k: v.float() for k, v in ck["ema_weights"].items()}


@cuda
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_cuda_graph_training_against_eager(tmp_path, precision):
    """The captured run repeats itself bit for bit, resumes exactly, records that it was captured, and ends at the
    eager run's weights (the same draws, kernels and order: equal up to the GPU's nondeterministic reductions)."""
    arrays = toy_arrays(n=64, n_val=8)
    spec = tiny_training(steps=40, precision=precision, checkpoint_every=1000)
    run = lambda name, **kw: train_model(  # noqa: E731
        arrays, "diffusion", TINY, spec, seed=2, device="cuda", progress=False, cache=tmp_path / name, **kw
    )
    ck_g, graphed = _weights(run("g", cuda_graph=True))
    _, again = _weights(run("g2", cuda_graph=True))
    _, eager = _weights(run("e", cuda_graph=False))
    partial = run("r", cuda_graph=True, stop_after=17)
    assert read_checkpoint(partial)["step"] == 17
    _, resumed = _weights(run("r", cuda_graph=True))
    assert ck_g["cuda_graph"] is True and ck_g["step"] == 40
    for k in graphed:
        assert torch.equal(graphed[k], again[k]), k
        assert torch.equal(graphed[k], resumed[k]), k
    diff = max((graphed[k] - eager[k]).abs().max().item() for k in graphed)
    scale = max(eager[k].abs().max().item() for k in eager)
    assert diff <= 1e-3 * scale, f"captured vs eager weights differ by {diff:.3g} (scale {scale:.3g})"
    assert all(torch.isfinite(v).all() for v in graphed.values())


@cuda
def test_cuda_graph_is_the_default_on_cuda_and_faster(tmp_path):
    arrays = toy_arrays(n=64)
    spec = tiny_training(steps=200, val_every=1000, checkpoint_every=1000)
    path = train_model(arrays, "diffusion", TINY, spec, device="cuda", progress=False, cache=tmp_path / "a")
    g = read_checkpoint(path)
    assert g.get("cuda_graph") is True
    meta_g = train_module.list_models("Toy", cache=tmp_path / "a")[0]
    train_model(arrays, "diffusion", TINY, spec, device="cuda", progress=False, cache=tmp_path / "b", cuda_graph=False)
    meta_e = train_module.list_models("Toy", cache=tmp_path / "b")[0]
    print(f"steps/s captured {meta_g['steps_per_s']:.0f}, eager {meta_e['steps_per_s']:.0f}")
    assert meta_g["steps_per_s"] > meta_e["steps_per_s"]
