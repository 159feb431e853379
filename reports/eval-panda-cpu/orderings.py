"""The Panda issue's orderings, each checked with a paired interval over the same contexts.

With the extra objects, on both Panda tasks: fraction valid MPD > Dprior+Cost > Dprior, and MPD's the largest (above
CVAE+Cost's too); MPD's end-effector errors below Dprior's; MPD's Vendi above every other method's. In the training
scene, the paper's CVAE-against-Dprior sentences (EnvWarehouse): Dprior more diverse than the CVAE, and nearer its
goal. Each line: A - B, mean [95 % bootstrap interval] over the contexts where both are finite
(``mpd.stats.paired``), and whether the interval excludes 0 in the claimed direction.

    python reports/eval-panda-cpu/orderings.py [results.parquet ...]   # default: this report's

Several tables: a later table's cells replace an earlier one's of the same task, method, parametrization and scene
(e.g. this report's, then reports/eval-panda-gpu-priors/results.parquet: the methods of the gpu-profile diffusion
priors beside the CVAE and the prior-free baselines of this one); the tables must share their test contexts.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

from mpd.stats import paired

HERE = Path(__file__).resolve().parent

# (scene: extra objects?, metric, A, B, higher is better, scale for printing, unit)
CLAIMS = [
    (True, "fraction_valid", "mpd", "dprior-cost", True, 100, "pp"),
    (True, "fraction_valid", "dprior-cost", "dprior", True, 100, "pp"),
    (True, "fraction_valid", "mpd", "dprior", True, 100, "pp"),
    (True, "fraction_valid", "mpd", "cvae-cost", True, 100, "pp"),
    (True, "ee_pos_error", "mpd", "dprior", False, 100, "cm"),
    (True, "ee_ori_error_deg", "mpd", "dprior", False, 1, "deg"),
    (True, "vendi", "mpd", "dprior", True, 1, ""),
    (True, "vendi", "mpd", "dprior-cost", True, 1, ""),
    (True, "vendi", "mpd", "gp-cost", True, 1, ""),
    (True, "vendi", "mpd", "rrtconnect-cost", True, 1, ""),
    (True, "vendi", "mpd", "cvae-cost", True, 1, ""),
    (False, "vendi", "dprior", "cvae", True, 1, ""),
    (False, "ee_pos_error", "dprior", "cvae", False, 100, "cm"),
    (False, "ee_ori_error_deg", "dprior", "cvae", False, 1, "deg"),
]


CELL = ["task", "method", "parametrization", "extra_objects"]


def combined(paths: list[Path]) -> pd.DataFrame:
    """The tables' rows, a later table's cells replacing an earlier one's; the test contexts must be the same."""
    df = pd.read_parquet(paths[0])
    for path in paths[1:]:
        new = pd.read_parquet(path)
        for task, d in new.groupby("task"):
            ours, theirs = set(df.contexts_hash[df.task == task]), set(d.contexts_hash)
            if ours and ours != theirs:
                raise SystemExit(f"{path}: {task}'s test contexts {sorted(theirs)} are not {sorted(ours)}")
        keys = set(map(tuple, new[CELL].drop_duplicates().to_numpy()))
        df = pd.concat([df[[k not in keys for k in map(tuple, df[CELL].to_numpy())]], new], ignore_index=True)
    return df


def main(paths: list[Path]) -> None:
    df = combined(paths)
    df = df[df.parametrization == "bspline"]
    for (task, extra), d in df.groupby(["task", df.extra_objects.astype(bool)]):
        scene = "extra objects" if extra else "training scene"
        print(f"\n{task}, {scene} ({d.context_index.nunique()} contexts)")
        for on_extra, metric, a, b, higher, scale, unit in CLAIMS:
            if on_extra != extra:
                continue
            va = d[d.method == a].set_index("context_index")[metric]
            vb = d[d.method == b].set_index("context_index")[metric]
            if va.empty or vb.empty:
                print(f"  {metric:17s} {a} vs {b}: not run")
                continue
            idx = va.index.intersection(vb.index)
            p = paired(va.loc[idx].to_numpy(), vb.loc[idx].to_numpy(), higher_is_better=higher)
            e = p.difference
            lo, hi = e.lo * scale, e.hi * scale
            holds = lo > 0 if higher else hi < 0
            sign = ">" if higher else "<"
            print(
                f"  {metric:17s} {a} {sign} {b}: {e.value * scale:+.1f} [{lo:+.1f}, {hi:+.1f}] {unit}"
                f" ({e.n} contexts): {'holds' if holds else 'NOT shown'}"
            )


if __name__ == "__main__":
    main([Path(a) for a in sys.argv[1:]] or [HERE / "results.parquet"])
