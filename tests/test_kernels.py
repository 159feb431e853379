"""The compiled kernels' registry and switch (:mod:`mpd.kernels`): every registered kernel's compiled path against its
torch reference on its realistic parity case (the Panda's URDF chain, EnvSpheres3D, the real costs and checker),
and the switch (the context manager, the environment variable) seen to change the path taken."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from mpd import kernels

KERNELS = kernels.registered()
CASES = [(name, dt) for name, k in KERNELS.items() for dt in k.dtypes]


def test_the_registry_lists_every_kernel():
    assert set(KERNELS) == {"fk", "collision", "self_collision", "ee_pose", "phase", "sphere"}
    assert {k.module for k in KERNELS.values()} == set(kernels.MODULES)


@pytest.mark.parametrize("name,dtype", CASES, ids=[f"{n}-{d}" for n, d in CASES])
def test_compiled_kernel_is_its_torch_reference(name, dtype):
    """The kernel's public entry point in both modes on its parity case: the same outputs (values and, for the
    costs, joint gradients) to the kernel's declared tolerance (``atol`` relative to the largest reference
    entry); each mode took its own path; the case is not trivial (a nonzero reference)."""
    run, tol = KERNELS[name].parity(getattr(torch, dtype))
    before = kernels.runs.copy()
    with kernels.use("compiled", name):
        got = run()
    mid = kernels.runs.copy()
    with kernels.use("torch", name):
        want = run()
    after = kernels.runs.copy()
    assert mid[name, "compiled"] > before[name, "compiled"] and mid[name, "torch"] == before[name, "torch"]
    assert after[name, "torch"] > mid[name, "torch"] and after[name, "compiled"] == mid[name, "compiled"]
    assert got.keys() == want.keys()
    for key in want:
        a, b = torch.as_tensor(np.asarray(got[key])), torch.as_tensor(np.asarray(want[key]))
        if b.dtype == torch.bool:
            assert torch.equal(a, b), key
            continue
        assert b.abs().max() > 0, f"{name}: {key} is zero, the case tests nothing"
        atol = tol["atol"] * float(b.abs().max())
        torch.testing.assert_close(a, b, rtol=tol["rtol"], atol=atol, msg=lambda m, k=key: f"{name} {k}: {m}")
    if name == "sphere":  # some states and edges valid, some not
        assert 0 < want["valid"].mean() < 1 and 0 < want["edges"].mean() < 1


def test_the_context_manager_selects_the_path():
    """``use`` switches all kernels or the named ones, nests, restores on exit, and refuses unknown names/modes."""
    assert kernels.mode() == "compiled" and kernels.mode("fk") == "compiled"
    with kernels.use("torch"):
        assert kernels.mode("fk") == "torch" and kernels.mode("collision") == "torch"
        with kernels.use("compiled", "collision"):
            assert kernels.mode("collision") == "compiled" and kernels.mode("fk") == "torch"
        assert kernels.mode("collision") == "torch"
    assert kernels.mode("fk") == "compiled"
    with kernels.use("torch", "fk"):
        assert kernels.mode("fk") == "torch" and kernels.mode("phase") == "compiled"
    with pytest.raises(ValueError, match="unknown kernel mode"):
        with kernels.use("numba"):
            pass
    with pytest.raises(ValueError, match="unknown kernels"):
        with kernels.use("torch", "nope"):
            pass
    # an FK on the Panda takes the path the switch says (a tensor that needs a gradient always takes torch's)
    from mpd.robots.robot import get_robot

    chain = get_robot("RobotPanda").chain
    q = torch.zeros(4, chain.dof)
    for mode, want in (("compiled", "compiled"), ("torch", "torch")):
        before = kernels.runs[("fk", want)]
        with kernels.use(mode):
            chain.forward(q)
        assert kernels.runs[("fk", want)] == before + 1
    before = kernels.runs[("fk", "torch")]
    chain.forward(q.clone().requires_grad_())
    assert kernels.runs[("fk", "torch")] == before + 1


def test_the_environment_variable_sets_the_mode(monkeypatch):
    monkeypatch.setenv(kernels.ENV, "torch")
    assert kernels.mode() == "torch" and kernels.mode("ee_pose") == "torch"
    with kernels.use("compiled", "ee_pose"):  # the context manager overrides it
        assert kernels.mode("ee_pose") == "compiled" and kernels.mode("fk") == "torch"
    monkeypatch.setenv(kernels.ENV, "compiled")
    assert kernels.mode("fk") == "compiled"
    monkeypatch.setenv(kernels.ENV, "fast")
    with pytest.raises(ValueError, match="unknown kernel mode 'fast'"):
        kernels.mode()
    # in a fresh process: the FK of the Panda takes the torch pass
    code = (
        "import torch; from mpd import kernels; from mpd.robots.robot import get_robot;"
        "get_robot('RobotPanda').chain.forward(torch.zeros(3, 7)); print(dict(kernels.runs))"
    )
    env = {**os.environ, kernels.ENV: "torch"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert "('fk', 'torch'): 1" in out and "'compiled'" not in out
