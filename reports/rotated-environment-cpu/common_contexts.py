"""Success and fraction valid by rotation on the contexts valid at every rotation (paired over the same contexts).

The report's tables average each rotation over the contexts valid in that scene (20 at 0 deg, 11 at 50 deg), so
their means mix a change of scene with a change of contexts; this table holds the contexts fixed.

    python reports/rotated-environment-cpu/common_contexts.py [results.parquet]   # default: this report's
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

HERE = Path(__file__).resolve().parent


def main(path: Path) -> None:
    df = pd.read_parquet(path)
    common = set.intersection(*(set(g.context_index) for _, g in df.groupby("rotation_deg")))
    d = df[df.context_index.isin(common)]
    print(f"{len(common)} contexts valid at every rotation: {sorted(common)}")
    for metric in ("success", "fraction_valid"):
        table = d.groupby(["method", "rotation_deg"])[metric].mean().unstack() * 100
        print(f"\n{metric} [%]\n{table.round(1).to_string()}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "results.parquet")
