"""The paper's "B-spline vs waypoints computation time" figure from a pytest-benchmark JSON of
``benchmarks/test_bench_sampling_time.py``: the time to denoise 1000 Panda trajectories (15 DDIM steps) and map them to
128 dense points, by representation (B-spline control points n_b, dense waypoints H = 128).

    python reports/sampling-time-bspline-waypoints/plot.py results.json [--pdf]   # figure.png (and .pdf) here
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).resolve().parent


def main(path: Path, pdf: bool = False) -> None:
    bench = json.loads(path.read_text())["benchmarks"]
    rows = sorted(
        ((b["extra_info"]["parametrization"], b["extra_info"]["n_params"], b["stats"]) for b in bench),
        key=lambda r: (r[0] != "bspline", r[1]),
    )
    labels = [f"B-spline\nn_b = {n}" if kind == "bspline" else f"waypoints\nH = {n}" for kind, n, _ in rows]
    med = [s["median"] for *_, s in rows]
    lo = [s["median"] - s["min"] for *_, s in rows]
    hi = [s["max"] - s["median"] for *_, s in rows]
    colors = ["#0b8a6f" if kind == "bspline" else "#7a5195" for kind, *_ in rows]
    fig, ax = plt.subplots(figsize=(6.4, 3.4), dpi=200)
    ax.bar(range(len(rows)), med, color=colors, yerr=[lo, hi], capsize=3)
    for i, (m, up) in enumerate(zip(med, hi, strict=True)):
        ax.text(i, m + up, f"{m:.1f} s", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(range(len(rows)), labels, fontsize=8)
    ax.set_ylabel("time [s], median (min-max)")
    info = bench[0]["extra_info"]
    ax.set_title(
        f"denoising {info['batch']} Panda trajectories, {info['ddim_steps']} DDIM steps, {info['threads']} CPU threads",
        fontsize=9,
    )
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    for ext in ("png", "pdf") if pdf else ("png",):
        fig.savefig(HERE / f"figure.{ext}")
    for (kind, n, s), m in zip(rows, med, strict=True):
        print(f"{kind:9s} {n:4d}: median {m:.2f} s [{s['min']:.2f}, {s['max']:.2f}]")


if __name__ == "__main__":
    main(Path(sys.argv[1]), pdf="--pdf" in sys.argv[2:])
