"""The compile-panda equivalence table: per task, method and scene, success / fraction valid / Vendi / end-effector
errors of the network variants in the results (eager or compiled, and the precisions run), and each context's paired
difference of fraction valid between every variant and eager fp32 (the reference).

Run: python reports/compile-panda/compare.py reports/compile-panda/results.parquet
"""

import sys

import pandas as pd

d = pd.read_parquet(sys.argv[1])
d["variant"] = (
    d["planner.network_compile"].map({True: "compiled", False: "eager"}) + " " + d["planner.network_precision"]
)
ref = "eager fp32"
others = sorted(v for v in d["variant"].unique() if v != ref)
head = ["task", "method", "scene", "contexts"]
for v in [ref, *others]:
    head += [f"valid {v}", f"Vendi {v}", f"EE cm / deg {v}"]
head += ["success"] + [f"valid: {v} - {ref}, paired mean [min, max] pp" for v in others]
print("| " + " | ".join(head) + " |")
print("|" + "---|" * len(head))
for (task, method, extra), g in d.groupby(["task", "method", "extra_objects"]):
    p = g.pivot_table(index="context_index", columns="variant", values="fraction_valid")
    row = [task.split("-")[0], method, "extra objects" if extra else "training", str(len(p))]
    for v in [ref, *others]:
        gv = g[g["variant"] == v]
        vendi = gv["vendi"].mean()
        row += [
            f"{100 * gv['fraction_valid'].mean():.1f}",
            "–" if pd.isna(vendi) else f"{vendi:.2f}",
            f"{100 * gv['ee_pos_error'].mean():.1f} / {gv['ee_ori_error_deg'].mean():.1f}",
        ]
    row.append(" / ".join(f"{100 * g[g['variant'] == v]['success'].mean():.0f}" for v in [ref, *others]))
    for v in others:
        diff = 100 * (p[v] - p[ref])
        row.append(f"{diff.mean():+.1f} [{diff.min():+.1f}, {diff.max():+.1f}]")
    print("| " + " | ".join(row) + " |")
