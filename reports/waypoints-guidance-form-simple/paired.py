"""The table of waypoints-guidance-form-simple: per prior, Dprior+Cost and every MPD cell (guided DDIM steps, M inner
iterations, lambda_prior) with its fraction valid, MPD - Dprior+Cost and (for the waypoint prior) waypoints - B-spline
at the same guidance, both paired over the contexts (mean [95 % interval], bootstrap over contexts), Vendi and
smoothness.

Run (from the repository root, with PYTHONPATH=.):
    python reports/waypoints-guidance-form-simple/paired.py reports/waypoints-guidance-form-simple/results.parquet
"""

import math
import sys

import pandas as pd

from mpd.stats import paired

KNOBS = ["planner.guide_fraction", "planner.n_inner_steps", "planner.prior_weight"]


def interval(a, b) -> str:
    e = paired(a.to_numpy(float), b.to_numpy(float)).difference
    return f"{100 * e.value:+.1f} [{100 * e.lo:+.1f}, {100 * e.hi:+.1f}]"


d = pd.read_parquet(sys.argv[1])
mpd_rows = d[d["method"] == "mpd"]
print(
    "| prior | method | guided steps | M | λ | valid % | MPD − Dprior+Cost (pp) | waypoints − B-spline (pp) | Vendi | "
    "smoothness |"
)
print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
for param, g in d.groupby("parametrization"):
    dc = g[g["method"] == "dprior-cost"].set_index("context_index")
    v, s = dc["vendi"].mean(), dc["smoothness"].mean()
    print(f"| {param} | Dprior+Cost | – | – | – | {100 * dc.fraction_valid.mean():.1f} | – | – | {v:.2f} | {s:.1f} |")
    for knobs, m in g[g["method"] == "mpd"].groupby(KNOBS):
        m = m.set_index("context_index").reindex(dc.index)
        other = mpd_rows[mpd_rows["parametrization"] != param]
        for k, val in zip(KNOBS, knobs):
            other = other[other[k] == val]
        versus = "–"
        if param == "waypoints":
            versus = interval(m.fraction_valid, other.set_index("context_index").fraction_valid.reindex(dc.index))
        row = [
            param, "MPD", str(math.ceil(knobs[0] * 15)), str(knobs[1]), f"{knobs[2]:g}",
            f"{100 * m.fraction_valid.mean():.1f}", interval(m.fraction_valid, dc.fraction_valid), versus,
            f"{m.vendi.mean():.2f}", f"{m.smoothness.mean():.1f}",
        ]  # fmt: skip
        print("| " + " | ".join(row) + " |")
