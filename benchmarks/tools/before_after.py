"""Before/after table of two runs of one spec, per (task, scene, method, parametrization): success, fraction valid
and Vendi, each as the mean over contexts with its 95 % interval (mpd.stats), and the number of contexts.

    python benchmarks/tools/before_after.py BEFORE_RUN AFTER_RUN [--out before-after.md] [--paired]

The two runs may use different contexts (e.g. a change of the evaluation protocol): the intervals are per run,
not paired. ``--paired`` adds after - before in fraction valid, paired over the contexts both rows of a cell hold
(the same ``context_index`` of the same contexts: check the runs' ``contexts_hash``), with its 95 % bootstrap.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from mpd import stats
from mpd.experiments.results import read_results
from mpd.viz.report_data import method_label

KEYS = ["task", "extra_objects", "method", "parametrization"]
METRICS = [
    ("success", True, 100.0, "success [%]"),
    ("fraction_valid", False, 100.0, "valid [%]"),
    ("vendi", False, 1.0, "Vendi"),
]


def _cell(df: pd.DataFrame, met: str, binary: bool, scale: float) -> str:
    if met not in df:
        return "–"
    e = stats.mean_interval(df[met].to_numpy(dtype=float), binary=binary)
    if e.n == 0 or pd.isna(e.value):
        return "–"
    if pd.isna(e.lo):
        return f"{scale * e.value:.1f}"
    return f"{scale * e.value:.1f} [{scale * e.lo:.1f}, {scale * e.hi:.1f}]"


def _paired_cell(b: pd.DataFrame, a: pd.DataFrame) -> str:
    """after - before of fraction valid (pp) over the contexts both hold, with its interval and their count."""
    both = (
        b.set_index("context_index")["fraction_valid"]
        .to_frame("b")
        .join(a.set_index("context_index")["fraction_valid"].to_frame("a"), how="inner")
    )
    if both.empty:
        return "–"
    d = stats.paired(both["a"].to_numpy(), both["b"].to_numpy()).difference
    if pd.isna(d.lo):
        return f"{100 * d.value:+.1f} ({len(both)})"
    return f"{100 * d.value:+.1f} [{100 * d.lo:+.1f}, {100 * d.hi:+.1f}] ({len(both)})"


def table(before: pd.DataFrame, after: pd.DataFrame, paired: bool = False) -> str:
    for d in (before, after):
        d["parametrization"] = d["parametrization"].fillna("bspline")
    cells = sorted(set(map(tuple, pd.concat([before[KEYS], after[KEYS]]).drop_duplicates().values.tolist())))
    pairs = " | ".join(f"{lab} before | {lab} after" for *_, lab in METRICS)
    head = f"| task | scene | method | {pairs} | contexts |"
    head += " valid, after − before, pp (contexts) |" if paired else ""
    lines = [head, "|" + " --- |" * (4 + 2 * len(METRICS) + paired)]
    for task, extra, method, par in cells:
        b, a = (
            d[(d.task == task) & (d.extra_objects == extra) & (d.method == method) & (d.parametrization == par)]
            for d in (before, after)
        )
        label = method_label(method) + (" (waypoints)" if par == "waypoints" else "")
        row = [task.split("-")[0], "extra objects" if extra else "training", label]
        for met, binary, scale, _ in METRICS:
            row += [_cell(b, met, binary, scale), _cell(a, met, binary, scale)]
        row.append(f"{len(b)} → {len(a)}")
        if paired:
            row.append(_paired_cell(b, a))
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--out", default=None)
    ap.add_argument("--paired", action="store_true", help="add after - before of fraction valid, paired by context")
    args = ap.parse_args()
    text = table(read_results(Path(args.before)), read_results(Path(args.after)), paired=args.paired)
    if args.out:
        Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
