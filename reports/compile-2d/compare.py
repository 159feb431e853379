"""The compile-2d equivalence table: per task, method and scene, success / fraction valid / Vendi of the four network
variants (eager or compiled, fp32 or bf16) and the paired difference of each context's fraction valid between the
compiled bf16 network (the fast path) and eager fp32 (the reference).

Run: python reports/compile-2d/compare.py reports/compile-2d/results.parquet
"""

import sys

import pandas as pd

d = pd.read_parquet(sys.argv[1])
d["variant"] = (
    d["planner.network_compile"].map({True: "compiled", False: "eager"}) + " " + d["planner.network_precision"]
)
order = ["eager fp32", "eager bf16", "compiled fp32", "compiled bf16"]
head = ["task", "method", "scene", "contexts"]
for v in order:
    head += [f"valid {v}", f"Vendi {v}"]
head += ["success (4 variants)", "valid: compiled bf16 - eager fp32, paired mean [min, max] pp"]
print("| " + " | ".join(head) + " |")
print("|" + "---|" * len(head))
for (task, method, extra), g in d.groupby(["task", "method", "extra_objects"]):
    p = g.pivot_table(index="context_index", columns="variant", values="fraction_valid")
    row = [task.split("-")[0], method, "extra objects" if extra else "training", str(len(p))]
    for v in order:
        gv = g[g["variant"] == v]
        vendi = gv["vendi"].mean()  # missing where no context has two valid samples
        row += [f"{100 * gv['fraction_valid'].mean():.1f}", "–" if pd.isna(vendi) else f"{vendi:.2f}"]
    row.append(" / ".join(f"{100 * g[g['variant'] == v]['success'].mean():.0f}" for v in order))
    diff = 100 * (p["compiled bf16"] - p["eager fp32"])
    row.append(f"{diff.mean():+.1f} [{diff.min():+.1f}, {diff.max():+.1f}]")
    print("| " + " | ".join(row) + " |")
