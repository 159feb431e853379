"""Device selection: CUDA when present, CPU otherwise; ``MPD_DEVICE`` overrides. And the arithmetic networks run in
on a device (:class:`Arithmetic`, decided by :func:`resolve`), for training (``TrainingSpec.precision``) and planning
(``PlannerSettings.network_precision``) alike."""

from __future__ import annotations

import contextlib
import functools
import os
from dataclasses import dataclass
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


PRECISIONS = ("auto", "fp32", "bf16")


@dataclass(frozen=True)
class Arithmetic:
    """The arithmetic a network runs in on a device, decided once by :func:`resolve` and used by the training step
    and by the planners alike: ``dtype`` ``"bf16"`` (autocast: weights stay float32; matrix products and
    convolutions in bf16 with float32 accumulation) or ``"fp32"``; ``requested`` what was asked for; ``cuda_graph``
    whether a training step on this device may be captured in a CUDA graph (``MPD_CUDA_GRAPH=0`` turns it off)."""

    device_type: str
    requested: str
    dtype: str
    native_bf16: bool
    cuda_graph: bool

    @property
    def bf16(self) -> bool:
        return self.dtype == "bf16"

    def autocast(self, cache_enabled: bool = True) -> contextlib.AbstractContextManager:
        """The context the network's forward passes run in: bf16 autocast, or nothing for fp32. ``cache_enabled``
        False for a step captured in a CUDA graph (the weight cache would hold the captured step's casts)."""
        if self.bf16:
            return torch.autocast(self.device_type, dtype=torch.bfloat16, cache_enabled=cache_enabled)
        return contextlib.nullcontext()

    def record(self) -> dict[str, str]:
        """What an artifact records of the decision (a model's meta; a plan records it as ``network_precision``)."""
        return {"arithmetic": self.dtype}


def resolve(device: torch.device | str, requested: str = "auto", name: str = "precision") -> Arithmetic:
    """The arithmetic of a network on ``device``: ``fp32``; ``bf16`` (emulated where the device has no native bf16,
    slowly); or for ``auto`` bf16 where the device computes it natively (CUDA's own test; on a CPU AVX512_BF16 or
    AMX) and fp32 elsewhere: without them oneDNN emulates bf16 and a training step of the profiles' networks is ~30x
    slower (measured on an AMD EPYC Zen 3, AVX2). ``MPD_BF16=emulate`` takes bf16 for native (for tests of the bf16
    path on any CPU). ``name`` names the setting in the error on a value other than auto, fp32 or bf16."""
    if requested not in PRECISIONS:
        raise ValueError(f"{name} must be auto, fp32 or bf16, got {requested!r}")
    device = torch.device(device)
    native = native_bf16(device)
    if requested == "auto":
        dtype = "bf16" if native or os.environ.get("MPD_BF16") == "emulate" else "fp32"
    else:
        dtype = requested
    graph = (
        device.type == "cuda"
        and os.environ.get("MPD_CUDA_GRAPH", "1") != "0"
        and hasattr(torch.cuda.CUDAGraph, "register_generator_state")
    )
    return Arithmetic(device.type, requested, dtype, native, graph)


def training_request(precision: str) -> str:
    """The request a training's ``precision`` makes: ``bf16`` asks for bf16 where the device has it natively (auto),
    ``fp32`` for fp32."""
    return "auto" if precision == "bf16" else "fp32"


def training_arithmetic(precision: str, device: torch.device | str) -> str:
    """The arithmetic (``fp32`` or ``bf16``) a training of ``precision`` runs in on ``device`` (:func:`resolve`)."""
    return resolve(device, training_request(precision)).dtype


def network_precision(requested: str, device: torch.device | str) -> str:
    """The precision a planner runs its network in for ``PlannerSettings.network_precision`` (:func:`resolve`)."""
    return resolve(device, requested, name="network_precision").dtype


def default_device() -> torch.device:
    name = os.environ.get("MPD_DEVICE")
    if name:
        return torch.device(name)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def synchronize(device: torch.device | str) -> None:
    """Wait for queued kernels, so that wall-clock timings measure the work (a no-op on CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
