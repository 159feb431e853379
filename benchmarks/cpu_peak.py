"""Nominal peak floating-point rate of this CPU, for the benchmarks' "achieved vs peak" figures (issue 15, item 6).

peak = cores used x clock x FLOP per cycle per core, where FLOP per cycle comes from the vector units the CPU
reports (``/proc/cpuinfo`` flags and family): an FMA counts 2 FLOP per lane.

- AMD Zen 4 (family 25 with AVX-512): AVX-512 runs on two 256-bit FMA pipes: 2 x 8 x 2 = 32 fp32 FLOP/cycle;
  ``vdpbf16ps`` (AVX512_BF16) does 2 bf16 products per fp32 lane: 64 bf16 FLOP/cycle.
- Intel with AVX-512 (two 512-bit FMA units): 64 fp32; AVX512_BF16 128; AMX (``amx_bf16``): 1024 bf16 per core.
- AVX2 + FMA (two 256-bit units): 32 fp32; bf16 falls back to fp32 arithmetic.

The clock is the one ``/proc/cpuinfo`` reports now (``cpu MHz``): a boost clock makes the true peak higher, so the
fraction of peak given is an upper bound on the headroom's complement, not a precise figure.
"""

from __future__ import annotations

from pathlib import Path


def _cpuinfo() -> dict[str, str]:
    out: dict[str, str] = {}
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return out
    for line in text.splitlines():
        if ":" in line:
            k, v = (s.strip() for s in line.split(":", 1))
            out.setdefault(k, v)
        elif not line.strip() and out:
            break  # the first processor is enough
    return out


def flop_per_cycle(info: dict[str, str] | None = None) -> dict[str, float]:
    """fp32 and bf16 FLOP per cycle per core from the CPU's flags (see the module docstring)."""
    info = _cpuinfo() if info is None else info
    flags = set(info.get("flags", "").split())
    vendor = info.get("vendor_id", "")
    family = int(info.get("cpu family", "0") or 0)
    if "avx512f" in flags:
        if vendor == "AuthenticAMD" and family == 25:  # Zen 4: AVX-512 on 256-bit datapaths
            fp32 = 32.0
            bf16 = 64.0 if "avx512_bf16" in flags else fp32
        else:
            fp32 = 64.0
            bf16 = 128.0 if "avx512_bf16" in flags else fp32
        if "amx_bf16" in flags:
            bf16 = 1024.0
    elif "avx2" in flags and "fma" in flags:
        fp32, bf16 = 32.0, 32.0
    else:
        fp32, bf16 = 8.0, 8.0
    return {"fp32": fp32, "bf16": bf16}


def peak_gflops(threads: int, info: dict[str, str] | None = None) -> dict:
    """Nominal fp32 / bf16 peak GFLOP/s of ``threads`` cores, with what it was computed from."""
    info = _cpuinfo() if info is None else info
    ghz = float(info.get("cpu MHz", "0") or 0) / 1000.0
    fpc = flop_per_cycle(info)
    return {
        "fp32": threads * ghz * fpc["fp32"],
        "bf16": threads * ghz * fpc["bf16"],
        "ghz": ghz,
        "flop_per_cycle": fpc,
        "cpu": info.get("model name", "?"),
    }
