"""The Panda issue's orderings, each checked with a paired interval over the same contexts.

With the extra objects, on both Panda tasks: fraction valid MPD > Dprior+Cost > Dprior; MPD's end-effector errors
below Dprior's; MPD's Vendi above every other method's. Each line: A - B, mean [95 % bootstrap interval] over the
contexts where both are finite (``mpd.stats.paired``), and whether the interval excludes 0 in the claimed direction.

    python reports/eval-panda-cpu/orderings.py [results.parquet]   # default: this report's
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

from mpd.stats import paired

HERE = Path(__file__).resolve().parent

# (metric, A, B, higher is better, scale for printing, unit)
CLAIMS = [
    ("fraction_valid", "mpd", "dprior-cost", True, 100, "pp"),
    ("fraction_valid", "dprior-cost", "dprior", True, 100, "pp"),
    ("fraction_valid", "mpd", "dprior", True, 100, "pp"),
    ("ee_pos_error", "mpd", "dprior", False, 100, "cm"),
    ("ee_ori_error_deg", "mpd", "dprior", False, 1, "deg"),
    ("vendi", "mpd", "dprior", True, 1, ""),
    ("vendi", "mpd", "dprior-cost", True, 1, ""),
    ("vendi", "mpd", "gp-cost", True, 1, ""),
    ("vendi", "mpd", "rrtconnect-cost", True, 1, ""),
]


def main(path: Path) -> None:
    df = pd.read_parquet(path)
    df = df[(df.parametrization == "bspline") & df.extra_objects.astype(bool)]
    for task, d in df.groupby("task"):
        print(f"\n{task}, extra objects ({d.context_index.nunique()} contexts)")
        for metric, a, b, higher, scale, unit in CLAIMS:
            va = d[d.method == a].set_index("context_index")[metric]
            vb = d[d.method == b].set_index("context_index")[metric]
            if va.empty or vb.empty:
                print(f"  {metric:17s} {a} vs {b}: not run")
                continue
            idx = va.index.intersection(vb.index)
            p = paired(va.loc[idx].to_numpy(), vb.loc[idx].to_numpy(), higher_is_better=higher)
            e = p.difference
            lo, hi = e.lo * scale, e.hi * scale
            holds = lo > 0 if higher else hi < 0
            sign = ">" if higher else "<"
            print(
                f"  {metric:17s} {a} {sign} {b}: {e.value * scale:+.1f} [{lo:+.1f}, {hi:+.1f}] {unit}"
                f" ({e.n} contexts): {'holds' if holds else 'NOT shown'}"
            )


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "results.parquet")
