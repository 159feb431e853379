"""A prior's learning curve as tables: snapshots of one training (copies of its ``last.pt``) evaluated by
``prior_misses.py`` (Dprior, Dprior+Cost and MPD, or a CVAE's CVAE and CVAE+Cost; the training scene and the extra
objects, the task's evaluation contexts), one row per snapshot, with 95 % intervals over the contexts and the paper's
adaptation comparison (MPD - Dprior+Cost with the extra objects, paired over the contexts).

Files are named ``<label>-<steps>-<method>[-extra].parquet`` (e.g. ``authors-40000-mpd-extra.parquet``), as
``prior_misses.py --out`` writes them:

    PYTHONPATH=. python benchmarks/tools/learning_curve.py /tmp/evals/*-[0-9]*-*.parquet --csv contexts.csv
    PYTHONPATH=. python benchmarks/tools/learning_curve.py contexts.csv   # the tables again from the per-context file
    PYTHONPATH=. python benchmarks/tools/learning_curve.py contexts.csv --versus authors:60000 cpu:24000  # paired

A file with a ``task`` column (several tasks' files combined) gives a table per task.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pandas as pd

from mpd.stats import bootstrap, paired, rate

NAME = re.compile(
    r"(?P<label>.+?)-(?P<steps>\d+)-(?P<method>dprior-cost|dprior|cvae-cost|cvae|mpd)(?P<extra>-extra)?\.parquet$"
)
METHODS = {"cvae": "CVAE", "cvae-cost": "CVAE+Cost", "dprior": "Dprior", "dprior-cost": "Dprior+Cost", "mpd": "MPD"}


def load(files: list[Path]) -> pd.DataFrame:
    """Per context: the fraction valid and whether any sample is valid, with the file's label, steps, method, scene."""
    rows = []
    for f in files:
        m = NAME.match(f.name)
        if m is None:
            raise ValueError(f"{f}: expected <label>-<steps>-<method>[-extra].parquet")
        steps = int(m["steps"])
        g = pd.read_parquet(f).groupby("context").valid
        rows.append(
            pd.DataFrame(
                {
                    "label": m["label"],
                    "steps": steps,
                    "method": m["method"],
                    "scene": "extra objects" if m["extra"] else "training",
                    "context": g.mean().index,
                    "valid": g.mean().to_numpy(),
                    "success": g.any().to_numpy().astype(float),
                }
            )
        )
    return pd.concat(rows, ignore_index=True)


def _cell(g: pd.DataFrame) -> str:
    v, s = bootstrap(g.valid), rate(g.success)
    return f"{100 * v.value:.1f} [{100 * v.lo:.1f}, {100 * v.hi:.1f}] / {100 * s.value:.0f} %"


def table(df: pd.DataFrame) -> str:
    """Markdown: a row per (label, steps), a column per (scene, method): fraction valid % [95 % CI] / success %,
    and MPD - Dprior+Cost with the extra objects (pp, paired bootstrap 95 %) when both were evaluated."""
    cols = [
        (sc, me)
        for sc in ("training", "extra objects")
        for me in METHODS
        if ((df.scene == sc) & (df.method == me)).any()
    ]
    adaptation = {("extra objects", "mpd"), ("extra objects", "dprior-cost")} <= set(cols)
    head = ["prior", "steps", *(f"{METHODS[me]}, {sc}" for sc, me in cols)]
    head += ["MPD − Dprior+Cost, extra objects (pp)"] if adaptation else []
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for (label, steps), g in df.groupby(["label", "steps"], sort=True):
        cells = []
        for sc, me in cols:
            c = g[(g.scene == sc) & (g.method == me)]
            cells.append(_cell(c) if len(c) else "")
        a = g[(g.scene == "extra objects") & (g.method == "mpd")].set_index("context").valid
        b = g[(g.scene == "extra objects") & (g.method == "dprior-cost")].set_index("context").valid
        diff = ""
        if len(a) and len(b):
            common = a.index.intersection(b.index)
            d = paired(a[common].to_numpy(), b[common].to_numpy()).difference
            diff = f"{100 * d.value:+.1f} [{100 * d.lo:+.1f}, {100 * d.hi:+.1f}]"
        lines.append("| " + " | ".join([label, str(steps), *cells, *([diff] if adaptation else [])]) + " |")
    return "\n".join(lines)


def versus(df: pd.DataFrame, a: str, b: str) -> str:
    """Markdown: prior ``a`` − prior ``b`` ("label:steps" each) per (scene, method), fraction valid paired over the
    contexts both ran (pp, 95 % bootstrap)."""

    def rows(ref: str) -> pd.DataFrame:
        label, steps = ref.rsplit(":", 1)
        return df[(df.label == label) & (df.steps == int(steps))]

    ra, rb = rows(a), rows(b)
    lines = [f"| scene | method | {a} − {b}, fraction valid (pp) | contexts |", "| --- | --- | --- | ---: |"]
    for sc, me in [(sc, me) for sc in ("training", "extra objects") for me in METHODS]:
        g = ra[(ra.scene == sc) & (ra.method == me)].set_index("context").valid
        h = rb[(rb.scene == sc) & (rb.method == me)].set_index("context").valid
        common = g.index.intersection(h.index)
        if len(common):
            d = paired(g[common].to_numpy(), h[common].to_numpy()).difference
            cell = f"{100 * d.value:+.1f} [{100 * d.lo:+.1f}, {100 * d.hi:+.1f}]"
            lines.append(f"| {sc} | {METHODS[me]} | {cell} | {len(common)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="<label>-<steps>-<method>[-extra].parquet files, or CSVs")
    parser.add_argument("--csv", type=Path, help="write the per-context values to this CSV")
    parser.add_argument("--versus", nargs=2, metavar=("A", "B"), help="paired A - B, each label:steps")
    args = parser.parse_args(argv)
    files, csv, pair = args.files, args.csv, args.versus
    df = pd.concat([pd.read_csv(f) for f in files]) if all(f.suffix == ".csv" for f in files) else load(files)
    if csv is not None:
        df.to_csv(csv, index=False, float_format="%.4g")
    tasks = df.groupby("task", sort=False) if "task" in df else [(None, df)]  # a combined file: a table per task
    for task, d in tasks:
        n = d.groupby("scene").context.nunique()
        print(f"\n## {task}\n" if task else "", table(d), sep="")
        if pair:
            print("\n" + versus(d, *pair))
        print("\ncontexts per scene: " + ", ".join(f"{k} {v}" for k, v in n.items()))
    print("fraction valid: the mean over contexts of each context's share of valid samples; success: a valid one")


if __name__ == "__main__":
    main()
