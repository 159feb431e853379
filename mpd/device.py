"""Device selection: CUDA when present, CPU otherwise; ``MPD_DEVICE`` overrides. And the precision the denoising
network runs in at planning time (``PlannerSettings.network_precision``)."""

from __future__ import annotations

import contextlib
import functools
import os
from pathlib import Path

import torch

BF16_CPU_FLAGS = ("avx512_bf16", "amx_bf16")  # native bf16 arithmetic (without them oneDNN emulates it, slowly)


@functools.cache
def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags (Linux ``/proc/cpuinfo``; empty elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def native_bf16(device: torch.device | str) -> bool:
    """Whether bf16 matrix arithmetic runs natively on the device: CUDA's own test, on a CPU AVX512_BF16 or AMX."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    if device.type == "cpu":
        return bool(cpu_flags() & set(BF16_CPU_FLAGS))
    return False


def can_compile(device: torch.device | str) -> bool:
    """Whether torch.compile (inductor) can build kernels for the device here: on a CPU it needs a C++ compiler
    (``CXX``, g++, c++ or clang++ on the PATH), on CUDA triton. The fast path is the default only where this holds;
    asked for explicitly (``network_compile = true``) it fails with a message naming the missing compiler."""
    import shutil

    device = torch.device(device)
    if device.type == "cuda":
        import importlib.util

        return importlib.util.find_spec("triton") is not None
    if device.type != "cpu":
        return False
    names = [os.environ["CXX"]] if os.environ.get("CXX") else []
    return any(shutil.which(n) for n in [*names, "g++", "c++", "clang++"])


def training_arithmetic(precision: str, device: torch.device | str) -> str:
    """The arithmetic a training of ``precision`` runs in on ``device``: bf16 autocast where the device has native
    bf16 arithmetic, fp32 elsewhere (without AVX512_BF16 / AMX, oneDNN emulates bf16 and a training step of the
    profiles' networks is ~30x slower: measured on an AMD EPYC Zen 3, AVX2). ``MPD_BF16=emulate`` forces bf16 there
    (for tests of the bf16 path on any CPU)."""
    if precision != "bf16":
        return "fp32"
    return "bf16" if native_bf16(device) or os.environ.get("MPD_BF16") == "emulate" else "fp32"


def network_precision(requested: str, device: torch.device | str) -> str:
    """The precision a planner runs its network in: ``fp32``, ``bf16``, or for ``auto`` bf16 where the device has
    native bf16 arithmetic and fp32 elsewhere."""
    if requested == "auto":
        return "bf16" if native_bf16(device) else "fp32"
    if requested not in ("fp32", "bf16"):
        raise ValueError(f"network_precision must be auto, fp32 or bf16, got {requested!r}")
    return requested


def network_autocast(precision: str, device: torch.device | str):
    """The context the network's forward passes run in: bf16 autocast (weights stay float32; matrix products and
    convolutions in bf16 with float32 accumulation), or nothing for fp32."""
    if precision == "bf16":
        return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def default_device() -> torch.device:
    name = os.environ.get("MPD_DEVICE")
    if name:
        return torch.device(name)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def synchronize(device: torch.device | str) -> None:
    """Wait for queued kernels, so that wall-clock timings measure the work (a no-op on CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
