"""The guidance-form tables: per task and scene, every MPD cell's fraction valid next to Dprior+Cost's, with MPD -
Dprior+Cost paired over the contexts (mean [95 % interval], bootstrap over contexts) and P(MPD better), Vendi and
success; the cells named by their guided steps (ceil(guide_fraction x 15)), M (n_inner_steps) and lambda_prior.

Run: python reports/guidance-form-2d/paired.py reports/guidance-form-2d/results.parquet
(or reports/guidance-form-2d-check/results.parquet)
"""

import math
import sys

import pandas as pd

from mpd.stats import paired

d = pd.read_parquet(sys.argv[1])
KNOBS = ["planner.guide_fraction", "planner.n_inner_steps", "planner.prior_weight"]
print("| task | scene | method | guided steps | M | lambda | contexts | success % | valid % | Vendi | "
      "MPD - Dprior+Cost, valid, pp | P(MPD better) |")  # fmt: skip
print("|" + "---|" * 12)
for (task, extra), g in d.groupby(["task", "extra_objects"]):
    dc = g[g["method"] == "dprior-cost"].set_index("context_index")["fraction_valid"]
    g = g.assign(order=g["method"].map({"dprior": 0, "dprior-cost": 1, "mpd": 2}))
    for keys, c in g.sort_values(["order", *KNOBS]).groupby(["method", *KNOBS], sort=False):
        method, f, m, lam = keys
        v = c.set_index("context_index")["fraction_valid"].reindex(dc.index)
        steps, mm, ll = (str(math.ceil(f * 15)), str(m), f"{lam:g}") if method == "mpd" else ("–", "–", "–")
        diff = p_better = "–"
        if method == "mpd":
            p = paired(v.to_numpy(), dc.to_numpy())
            e, b = p.difference, p.p_improvement
            diff = f"{100 * e.value:+.1f} [{100 * e.lo:+.1f}, {100 * e.hi:+.1f}]"
            p_better = f"{b.value:.2f} [{b.lo:.2f}, {b.hi:.2f}]"
        vendi = c["vendi"].mean()
        row = [
            task.split("-")[0], "extra objects" if extra else "training", method, steps, mm, ll, str(len(c)),
            f"{100 * c['success'].mean():.0f}", f"{100 * v.mean():.1f}", "–" if pd.isna(vendi) else f"{vendi:.2f}",
            diff, p_better,
        ]  # fmt: skip
        print("| " + " | ".join(row) + " |")
