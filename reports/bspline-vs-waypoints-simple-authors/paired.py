"""Sec. V-F's table: per scene and method, the B-spline prior's and the waypoint prior's means over the contexts
(success, fraction valid, Vendi, smoothness and path length of the valid samples, planning time) and waypoints -
B-spline paired over the contexts (mean [95 % interval], bootstrap over contexts; a metric undefined in a context,
e.g. Vendi without two valid samples, drops that context from its pair).

Run (from the repository root, with PYTHONPATH=.):
    python reports/bspline-vs-waypoints-simple-authors/paired.py \\
        reports/bspline-vs-waypoints-simple-authors/results.parquet
"""

import sys

import pandas as pd

from mpd.stats import paired

METRICS = [  # column, label, scale, format
    ("success", "success %", 100, ".0f"),
    ("fraction_valid", "valid %", 100, ".1f"),
    ("vendi", "Vendi", 1, ".2f"),
    ("smoothness", "smoothness", 1, ".2f"),
    ("path_length", "path length", 1, ".3f"),
    ("time_total", "time s", 1, ".3f"),
]
d = pd.read_parquet(sys.argv[1])
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
