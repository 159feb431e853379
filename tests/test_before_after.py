"""benchmarks/tools/before_after.py --paired: after - before of fraction valid per cell, aligned by context index over
the contexts both runs hold, against the differences computed by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd


def _rows(values: dict[int, float]) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "task": "EnvSimple2D-RobotPointMass2D",
            "extra_objects": False,
            "method": "dprior",
            "parametrization": "bspline",
            "context_index": list(values),
            "fraction_valid": list(values.values()),
            "success": [v > 0 for v in values.values()],
        }
    )


def test_paired_column_is_the_mean_difference_over_the_shared_contexts(bench_tool):
    rng = np.random.default_rng(0)
    before = {i: float(v) for i, v in enumerate(rng.uniform(0, 1, 12))}
    # the after run in another order, missing contexts 0 and 1, with context 12 that the before run lacks
    after = {i: float(v) for i, v in zip(range(12, 1, -1), rng.uniform(0, 1, 11), strict=True)}
    text = bench_tool("before_after").table(_rows(before), _rows(after), paired=True)
    row = next(line for line in text.splitlines() if "| Dprior |" in line)
    shared = sorted(set(before) & set(after))
    by_hand = 100 * np.mean([after[i] - before[i] for i in shared])
    cell = row.strip(" |").split(" | ")[-1]
    assert cell.startswith(f"{by_hand:+.1f} [") and cell.endswith(f"({len(shared)})")
    lo, hi = (float(x) for x in cell[cell.index("[") + 1 : cell.index("]")].split(", "))
    assert lo < by_hand < hi
    # without --paired the table has no such column
    assert "after − before" not in bench_tool("before_after").table(_rows(before), _rows(after))
