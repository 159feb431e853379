"""Sec. V-F's table: per scene and method, the B-spline prior's and the waypoint prior's means over the contexts
(the metrics of every report's summary table that the run has: success, fraction valid, Vendi, smoothness and
path length of the valid samples, planning time) and waypoints - B-spline paired over the contexts (mean [95 %
interval], bootstrap over contexts; a metric undefined in a context, e.g. Vendi without two valid samples, drops that
context from its pair).

Run (from the repository root, with PYTHONPATH=.):
    python reports/bspline-vs-waypoints-simple-authors/paired.py \\
        reports/bspline-vs-waypoints-simple-authors/results.parquet
"""

import sys

import pandas as pd

from mpd.stats import paired
from mpd.viz.report_data import SUMMARY  # (column, header, scale, format) of every report's summary table

d = pd.read_parquet(sys.argv[1])
# the summary's metrics this run has (a joint-goal task's EE errors are 0 throughout); "{:.1f}" -> ".1f"
METRICS = [(col, head, k, fmt[2:-1]) for col, head, k, fmt in SUMMARY if d[col].fillna(0).ne(0).any()]
print("| scene | method | contexts | metric | B-spline | waypoints | waypoints − B-spline |")
print("|" + "---|" * 7)
for (extra, _order), g in d.groupby(["extra_objects", d["method"].map({"dprior": 0, "dprior-cost": 1, "mpd": 2})]):
    b = g[g["parametrization"] == "bspline"].set_index("context_index")
    w = g[g["parametrization"] == "waypoints"].set_index("context_index").reindex(b.index)
    name = b["method"].iloc[0]
    for col, label, k, fmt in METRICS:
        e = paired(k * w[col].to_numpy(float), k * b[col].to_numpy(float)).difference
        row = [
            "extra objects" if extra else "training", name, str(len(b)), label,
            f"{k * b[col].mean():{fmt}}", f"{k * w[col].mean():{fmt}}",
            f"{e.value:+{fmt}} [{e.lo:+{fmt}}, {e.hi:+{fmt}}] ({e.n})",
        ]  # fmt: skip
        print("| " + " | ".join(row) + " |")
