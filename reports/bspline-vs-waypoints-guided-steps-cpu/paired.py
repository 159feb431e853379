"""The table of bspline-vs-waypoints-guided-steps-cpu: per task and number of guided DDIM steps, MPD's fraction
valid, smoothness and Vendi with each prior and waypoints - B-spline, and MPD - Dprior+Cost per prior, all paired
over the contexts (mean [95 % interval], bootstrap over contexts).

Run (from the repository root, with PYTHONPATH=.):
    python reports/bspline-vs-waypoints-guided-steps-cpu/paired.py \\
        reports/bspline-vs-waypoints-guided-steps-cpu/results.parquet
"""

import sys

import pandas as pd

from mpd.stats import paired

COLUMNS = [("fraction_valid", 100, ".1f"), ("smoothness", 1, ".2f"), ("vendi", 1, ".2f")]


def interval(a, b, k=100, fmt=".1f") -> str:
    e = paired(a.to_numpy(float), b.to_numpy(float)).difference
    return f"{k * e.value:+{fmt}} [{k * e.lo:+{fmt}}, {k * e.hi:+{fmt}}]"


d = pd.read_parquet(sys.argv[1])
print(
    "| task | guided steps | contexts | valid % B-spline | waypoints | waypoints − B-spline | smoothness B-spline | "
    "waypoints | waypoints − B-spline | Vendi B-spline | waypoints | waypoints − B-spline | MPD − Dprior+Cost, "
    "B-spline | MPD − Dprior+Cost, waypoints |"
)
print("| --- |" + " ---: |" * 13)
for task, g in d.groupby("task"):
    for fraction in (0.3, 0.2):
        m = g[(g["method"] == "mpd") & (g["planner.guide_fraction"] == fraction)]
        b = m[m["parametrization"] == "bspline"].set_index("context_index")
        w = m[m["parametrization"] == "waypoints"].set_index("context_index").reindex(b.index)
        row = [task.split("-")[0], "3" if fraction == 0.2 else "5", str(len(b))]
        for col, k, fmt in COLUMNS:
            row += [f"{k * b[col].mean():{fmt}}", f"{k * w[col].mean():{fmt}}", interval(w[col], b[col], k, fmt)]
        for param, x in (("bspline", b), ("waypoints", w)):
            dc = g[(g["method"] == "dprior-cost") & (g["parametrization"] == param)].set_index("context_index")
            row.append(interval(x["fraction_valid"], dc["fraction_valid"].reindex(b.index)))
        print("| " + " | ".join(row) + " |")
