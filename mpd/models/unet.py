"""Temporal U-Net (Janner et al. 2022, "Diffuser") over the control-point axis, FiLM-conditioned.

Input and output are ``(B, H, d)``: H control points (or waypoints) of d joints. Internally the tensor is
``(B, channels, H)`` and 1-D convolutions run along H, acting as a low-pass filter between neighbouring
control points. Layout, with ``dims = [d, dim*m_1, ..., dim*m_L]``:

* down level i: two residual temporal blocks ``dims[i] -> dims[i+1]``, then a stride-2 conv (except on the
  last level);
* mid: two residual blocks at ``dims[L]``;
* up levels L-1 .. 1: concatenate the skip of the down level at the same resolution, two residual blocks
  ``2 dims[i+1] -> dims[i]``, then a transposed-conv upsampling (as in Diffuser, the first level's output is
  not used as a skip);
* a conv block and a 1x1 conv back to d.

Each residual block is modulated by FiLM on ``cond``: a per-channel scale and shift from a linear layer.
For the diffusion model ``cond`` = [sinusoidal step embedding -> MLP, context embedding].
H is padded (edge values) to a multiple of ``2^(L-1)`` and cropped back, so any H works.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence

import torch
from torch import nn
from torch.nn import functional as F

KERNEL_SIZE = 5
N_GROUPS = 8
# The compiled CPU network's kernels called from generated C++ instead of a Python wrapper: a pass of the Panda
# U-Net (~100 kernels) spends a sizeable part of its time in the Python wrapper otherwise, and compiling takes no
# longer (benchmarks/test_bench_plans.py measures the plans).
CPU_CPP_WRAPPER = True


class SinusoidalPosEmb(nn.Module):
    """Transformer-style embedding of a (possibly fractional) diffusion step."""

    def __init__(self, dim: int):
        super().__init__()
        if dim % 2 or dim < 4:
            raise ValueError(f"time embedding dimension must be even and >= 4, got {dim}")
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(torch.arange(half, device=t.device, dtype=torch.float32) * (-math.log(10000.0) / (half - 1)))
        arg = t.float()[:, None] * freqs[None, :]
        return torch.cat([arg.sin(), arg.cos()], dim=-1)


def conv(m: nn.Module, h: torch.Tensor) -> torch.Tensor:
    """Apply the 1-D (transposed) convolution ``m`` to ``(B, C, H)``, or to ``(B, C, 1, H)`` in channels-last memory
    format as the same convolution in 2-D (the CPU inference path of :class:`TemporalUnet`). The 4-D weight is a
    channels-last copy kept on the module and rebuilt whenever the weight changes (its version counter, storage,
    dtype or device)."""
    if isinstance(m, nn.Identity) or h.ndim == 3:
        return m(h)
    stride, padding = (1, m.stride[0]), (0, m.padding[0])
    if torch.compiler.is_compiling():
        # traced by torch.compile: the 4-D weight as a function of the parameter (inductor's freezing folds it into
        # a constant), not the cache, whose attribute writes would recompile the graph
        w4 = m.weight.unsqueeze(2)
        if isinstance(m, nn.ConvTranspose1d):
            return F.conv_transpose2d(h, w4, m.bias, stride=stride, padding=padding)
        return F.conv2d(h, w4, m.bias, stride=stride, padding=padding)
    w = m.weight
    key = (w._version, w.data_ptr(), w.dtype, w.device)
    if getattr(m, "_w4_key", None) != key:
        m._w4 = w.detach().unsqueeze(2).contiguous(memory_format=torch.channels_last)
        m._w4_key = key
    if isinstance(m, nn.ConvTranspose1d):
        return F.conv_transpose2d(h, m._w4, m.bias, stride=stride, padding=padding)
    return F.conv2d(h, m._w4, m.bias, stride=stride, padding=padding)


# Above this, mish(x) = x in float32 and float64 to the last bit (tanh(softplus(x)) rounds to 1), and e^x (e^x + 2)
# would overflow float32.
MISH_LINEAR_FROM = 20.0


def mish(x: torch.Tensor) -> torch.Tensor:
    """Mish, x tanh(softplus(x)), written with one exponential: tanh(log(1 + e^x)) = n / (n + 2), n = e^x (e^x + 2).

    The form the compiled network uses. Inductor lowers ``F.mish`` to an exponential, a log1p and a tanh per
    element; this is one exponential and one division, which makes the compiled U-Net pass faster end to end
    (benchmarks/test_bench_models.py). Equal to ``F.mish`` to float rounding (tests); the eager network keeps
    ``nn.Mish`` (one ATen kernel there)."""
    e = torch.exp(torch.clamp(x, max=MISH_LINEAR_FROM))
    n = e * (e + 2)
    return torch.where(x > MISH_LINEAR_FROM, x, x * n / (n + 2))


class Conv1dBlock(nn.Sequential):
    """Conv1d -> GroupNorm -> Mish, length preserving."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int = KERNEL_SIZE, n_groups: int = N_GROUPS):
        super().__init__(
            nn.Conv1d(c_in, c_out, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(n_groups, c_out),
            nn.Mish(),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self[1](conv(self[0], x))
        return mish(h) if torch.compiler.is_compiling() else self[2](h)


class ResidualTemporalBlock(nn.Module):
    """Two conv blocks with FiLM on the first one's output, plus a (1x1-projected) residual path."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel_size: int = KERNEL_SIZE):
        super().__init__()
        self.block1 = Conv1dBlock(c_in, c_out, kernel_size)
        self.block2 = Conv1dBlock(c_out, c_out, kernel_size)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.residual = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor, film: torch.Tensor | None = None) -> torch.Tensor:
        """``film``: this block's ``self.film(cond)`` when the caller computed it (see ``TemporalUnet._films``)."""
        h = self.block1(x)
        film = self.film(cond) if film is None else film
        scale, shift = film.view(*film.shape, *(1,) * (x.ndim - 2)).chunk(2, dim=1)
        # (1 + scale) so that a zero FiLM output is the identity modulation
        h = self.block2(h * (1 + scale) + shift)
        return h + conv(self.residual, x)


def downsample(channels: int) -> nn.Module:
    return nn.Conv1d(channels, channels, 3, stride=2, padding=1)


def upsample(channels: int) -> nn.Module:
    return nn.ConvTranspose1d(channels, channels, 4, stride=2, padding=1)


def level_channels(dof: int, dim: int, dim_mults: Sequence[int]) -> list[tuple[int, int]]:
    """(in, out) channels of each down level."""
    if not dim_mults:
        raise ValueError("unet_dim_mults must not be empty")
    dims = [dof] + [dim * m for m in dim_mults]
    for c in dims[1:]:
        if c % N_GROUPS:
            raise ValueError(f"U-Net channel count {c} is not a multiple of the {N_GROUPS} GroupNorm groups")
    return list(zip(dims[:-1], dims[1:]))


def padded_horizon(horizon: int, n_levels: int) -> int:
    """Smallest multiple of 2^(n_levels - 1) that is >= horizon."""
    f = 2 ** (n_levels - 1)
    return -(-horizon // f) * f


def pad_horizon(x: torch.Tensor, n_levels: int) -> torch.Tensor:
    """Pad ``(B, C, H)`` at the end of H by repeating the last column."""
    h = x.shape[-1]
    extra = padded_horizon(h, n_levels) - h
    return F.pad(x, (0, extra), mode="replicate") if extra else x


def _frozen(fn: Callable) -> Callable:
    """``fn`` (a torch.compile'd inference forward) called with dynamo's ``prepare_freezing``: dynamo reads the
    global ``freezing`` setting, not the one given in ``torch.compile``'s options, to decide whether the module's
    parameters enter the graph as constants; without it inductor's freezing has nothing to freeze (the weights stay
    graph inputs: cast to bfloat16 and re-laid out on every call, never prepacked for oneDNN)."""

    def call(*args):
        with torch._dynamo.config.patch(prepare_freezing=True):
            return fn(*args)

    return call


def shared_step(t: int | torch.Tensor) -> bool:
    """Whether ``t`` is one diffusion step for the whole batch (an int, a scalar or a one-element tensor)."""
    return not isinstance(t, torch.Tensor) or t.numel() == 1


def as_step_tensor(t: int | torch.Tensor, batch: int, device: torch.device) -> torch.Tensor:
    """A diffusion step given as an int, a scalar or a ``(B,)`` tensor -> ``(B,)`` tensor on ``device``."""
    t = torch.as_tensor(t, device=device)
    if t.ndim == 0:
        t = t.expand(batch)
    if t.shape != (batch,):
        raise ValueError(f"diffusion step must be a scalar or have shape ({batch},), got {tuple(t.shape)}")
    return t


def down_path(levels: list[tuple[int, int]], cond_dim: int) -> nn.ModuleList:
    """Per level: [residual block in -> out, residual block out -> out, stride-2 conv (identity on last)]."""
    downs = nn.ModuleList()
    for i, (c_in, c_out) in enumerate(levels):
        last = i == len(levels) - 1
        downs.append(
            nn.ModuleList(
                [
                    ResidualTemporalBlock(c_in, c_out, cond_dim),
                    ResidualTemporalBlock(c_out, c_out, cond_dim),
                    nn.Identity() if last else downsample(c_out),
                ]
            )
        )
    return downs


def up_path(levels: list[tuple[int, int]], cond_dim: int, skips: bool) -> nn.ModuleList:
    """Levels L-1 .. 1: [residual block (2 out or out) -> in, residual block in -> in, upsampling]; the first
    block takes twice the channels when the down level's output is concatenated (``skips``)."""
    ups = nn.ModuleList()
    for c_in, c_out in reversed(levels[1:]):
        ups.append(
            nn.ModuleList(
                [
                    ResidualTemporalBlock((2 if skips else 1) * c_out, c_in, cond_dim),
                    ResidualTemporalBlock(c_in, c_in, cond_dim),
                    upsample(c_in),
                ]
            )
        )
    return ups


class TemporalUnet(nn.Module):
    """eps_theta(x_t, t, context embedding): ``(B, H, d) -> (B, H, d)`` for any H."""

    def __init__(
        self,
        dof: int,
        context_dim: int,
        dim: int = 32,
        dim_mults: Sequence[int] = (1, 2, 4),
        time_emb_dim: int = 32,
    ):
        super().__init__()
        self.dof = dof
        self.n_levels = len(dim_mults)
        levels = level_channels(dof, dim, dim_mults)
        self.time_mlp = nn.Sequential(
            SinusoidalPosEmb(time_emb_dim),
            nn.Linear(time_emb_dim, 4 * time_emb_dim),
            nn.Mish(),
            nn.Linear(4 * time_emb_dim, time_emb_dim),
        )
        cond_dim = time_emb_dim + context_dim
        self.downs = down_path(levels, cond_dim)
        mid = levels[-1][1]
        self.mid1 = ResidualTemporalBlock(mid, mid, cond_dim)
        self.mid2 = ResidualTemporalBlock(mid, mid, cond_dim)
        self.ups = up_path(levels, cond_dim, skips=True)
        top = levels[0][1]
        self.final = nn.Sequential(Conv1dBlock(top, top), nn.Conv1d(top, dof, 1))
        # the CPU inference path (no autograd): False runs the 1-D convolutions everywhere, its reference
        self.channels_last_2d = True
        self._generation = 0  # of the compiled graph (see compiled)

    def _films(self, cond: torch.Tensor) -> Iterator[torch.Tensor]:
        """Every residual block's FiLM output, in the order the forward calls the blocks, from one product: they all
        read the same Mish(cond), so their weights stacked are one linear layer (inside the compiled graph, whose
        freezing folds the stacking into one constant; 1 call instead of 14-16 oneDNN calls on a single row)."""
        blocks = [b for r1, r2, _ in self.downs for b in (r1, r2)] + [self.mid1, self.mid2]
        blocks += [b for r1, r2, _ in self.ups for b in (r1, r2)]
        lin = [b.film[1] for b in blocks]
        out = F.linear(F.mish(cond), torch.cat([m.weight for m in lin]), torch.cat([m.bias for m in lin]))
        return iter(out.split([m.out_features for m in lin], dim=1))

    def compiled(self) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
        """This network's forward compiled by torch.compile (inductor) for inference: weights frozen into the graph
        (``freezing``: constant-folded, cast and prepacked for oneDNN once on a CPU; see :func:`_frozen`), one graph
        per input shape and autocast state (``dynamic=False``). Call it under ``torch.no_grad()`` with the step as a
        tensor, ``(B,)`` or ``(1,)`` for one step for the whole batch (a Python int would be compiled as a
        constant). Kept on the module and rebuilt when a parameter changes (its version counter or storage), since
        frozen weights would otherwise go stale. The first call per shape compiles (tens of seconds on a CPU);
        ``PlannerSettings.network_compile`` turns it on for a planner. On a CPU the graph's kernels are called from
        generated C++ (inductor's ``cpp_wrapper``, :data:`CPU_CPP_WRAPPER`) rather than from Python."""
        key = self._weights_key()
        held = self.__dict__.get("_compiled")
        if held is None or held[0] != key:
            options = {"freezing": True}
            if next(self.parameters()).device.type == "cpu":
                options["cpp_wrapper"] = CPU_CPP_WRAPPER
            # a new generation: dynamo's cached graphs of this forward hold the old weights as constants, and their
            # guards (the same module, the same parameter objects) would still pass; the generation is guarded on
            self._generation = getattr(self, "_generation", 0) + 1
            held = self.__dict__["_compiled"] = (
                key,
                _frozen(torch.compile(self.forward, dynamic=False, options=options)),
            )
        return held[1]

    def _weights_key(self) -> tuple:
        """The parameters' version counters, storages, dtypes and devices: what a frozen graph depends on. The
        parameters are listed once with the dictionaries that hold them (walking the modules for every
        pass was a visible part of a small network's pass); a parameter replaced by another object is seen there."""
        refs = self.__dict__.get("_param_refs")
        if refs is None or any(d.get(name) is not p for d, name, p in refs):
            refs = [(m._parameters, name, p) for m in self.modules() for name, p in m._parameters.items()]
            refs = self.__dict__["_param_refs"] = [r for r in refs if r[2] is not None]
        return tuple((p._version, p.data_ptr(), p.dtype, p.device) for _, _, p in refs)

    def __getstate__(self) -> dict:
        # a copy or a pickle of the module never carries a compiled graph (it is rebuilt on demand)
        state = super().__getstate__()
        state.pop("_compiled", None)
        state.pop("_param_refs", None)
        return state

    def forward(self, x: torch.Tensor, t: int | torch.Tensor, context_emb: torch.Tensor) -> torch.Tensor:
        if x.ndim != 3 or x.shape[-1] != self.dof:
            raise ValueError(f"expected x of shape (B, H, {self.dof}), got {tuple(x.shape)}")
        b, horizon, _ = x.shape
        # read while tracing, so that dynamo guards on the compiled graph's generation (see compiled)
        if torch.compiler.is_compiling() and getattr(self, "_generation", 0) < 0:
            raise AssertionError("a compiled graph's generation is never negative")
        # one step and one context for the whole batch (sampling): the step embedding and every FiLM layer run on
        # one row, broadcast over the batch (not the same products on every row)
        rows = 1 if context_emb.shape[0] == 1 and shared_step(t) else b
        if context_emb.shape[0] != rows:
            context_emb = context_emb.expand(rows, -1)
        cond = torch.cat([self.time_mlp(as_step_tensor(t, rows, x.device)), context_emb], dim=-1)
        h = pad_horizon(x.transpose(1, 2), self.n_levels)
        # CPU inference: the convolutions as channels-last 2-D ones (B, C, 1, H), which oneDNN runs 1.18-1.26x faster
        # end to end at batch 100 on an Intel Xeon and an AMD Zen 4 (`benchmarks/test_bench_models.py`); the same
        # numbers to float32 rounding (tests)
        four_d = self.channels_last_2d and x.device.type == "cpu" and not torch.is_grad_enabled()
        if four_d:
            h = h.unsqueeze(2).contiguous(memory_format=torch.channels_last)
        # compiled: every block's FiLM from one product; eager: None for every block (each computes its own)
        films = self._films(cond) if torch.compiler.is_compiling() else iter(lambda: None, 0)
        skips = []
        for i, (res1, res2, down) in enumerate(self.downs):
            h = res2(res1(h, cond, next(films)), cond, next(films))
            if i > 0:  # level 0 is at full resolution, where no up level concatenates a skip
                skips.append(h)
            h = conv(down, h)
        h = self.mid2(self.mid1(h, cond, next(films)), cond, next(films))
        for res1, res2, up in self.ups:
            h = torch.cat([h, skips.pop()], dim=1)
            h = conv(up, res2(res1(h, cond, next(films)), cond, next(films)))
        h = conv(self.final[1], self.final[0](h))
        if four_d:
            h = h[:, :, 0]
        return h[..., :horizon].transpose(1, 2)
