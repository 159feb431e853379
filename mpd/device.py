"""Device selection: CUDA when present, CPU otherwise; ``MPD_DEVICE`` overrides."""

from __future__ import annotations

import os

import torch


def default_device() -> torch.device:
    name = os.environ.get("MPD_DEVICE")
    if name:
        return torch.device(name)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def synchronize(device: torch.device | str) -> None:
    """Wait for queued kernels, so that wall-clock timings measure the work (a no-op on CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
