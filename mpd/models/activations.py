"""Mish (Misra 2019), ``x * tanh(softplus(x))``, computed with one exponential on the CPU.

PyTorch's CPU kernel for ``F.mish`` (torch 2.13) takes ~6-9 ns an element where an exponential takes ~0.3 ns
(``benchmarks/test_bench_models.py::test_mish``), so in the U-Net's inference passes at batch 100 it was ~20 % of
the time. With ``e = exp(x)``, ``tanh(softplus(x)) = ((1 + e)^2 - 1) / ((1 + e)^2 + 1) = n / (n + 2)`` where
``n = e (e + 2)``: five vectorized elementwise ops. ``x`` is clamped at 20 inside the exponential (beyond it
``n / (n + 2)`` is 1 in float32 and bfloat16 alike), so nothing overflows. Other devices (CUDA: one fused kernel)
keep ``F.mish``. Same values as ``F.mish`` to float32 rounding, same gradient (autograd through the formula);
``tests/test_models.py`` checks both.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

CLAMP = 20.0


def mish(x: torch.Tensor) -> torch.Tensor:
    """Mish of ``x``: the one-exponential formula on the CPU, ``F.mish`` elsewhere."""
    if x.device.type != "cpu":
        return F.mish(x)
    e = torch.exp(x.clamp(max=CLAMP))
    n = e * (e + 2)
    return x * n / (n + 2)


class Mish(nn.Module):
    """``nn.Mish`` with :func:`mish` (no parameters: checkpoints are unchanged)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return mish(x)
