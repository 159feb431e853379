"""Why a 2-D prior's samples are invalid: how deep the invalid ones go into which obstacle, and how the fraction valid
moves with the sampler's steps (a sampler-bound prior gains from more steps, a training-bound one does not).

    PYTHONPATH=. python benchmarks/tools/prior_misses.py --task EnvNarrowPassageDense2D-RobotPointMass2D \
        --contexts 50 --samples 100 --out /tmp/misses.parquet
    PYTHONPATH=. python benchmarks/tools/prior_misses.py summary /tmp/misses.parquet

For each context (``--contexts-from``: drawn in the training scene by mpd.data.eval_contexts.sampled_contexts, or the
task's ``paper`` dataset's own contexts: those it was trained on, those held out, or the evaluations' held-out ones,
whose start and goal are at least the task's min_start_goal_distance apart) and each sampler variant,
Dprior's samples with the task's shipped default prior (eager fp32); per sample: valid, collision-free, limits, the
deepest point's clearance (signed distance minus the robot's radius; negative: inside) and the kind of the obstacle
nearest to it (a wall of the passage, a sphere, a box), and the context's start-goal distance. ``summary FILE``
prints the tables of a stored run, the fraction valid by start-goal distance too.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

VARIANTS = {  # name: planner settings
    "ddim 15 (config)": {},
    "ddim 50": {"ddim_steps": 50},
    "ddim 15, eta 1": {"eta": 1.0},
}


def contexts(task, n: int, source: str) -> tuple[np.ndarray, np.ndarray]:
    """(q_start, q_goal) of n contexts: drawn in the training scene (``sampled``), or the forward paths' contexts of
    the task's ``paper`` dataset in its ``train`` split or held out (``held-out``: test, then val), or the evaluations'
    held-out contexts (``task``: mpd.data.eval_contexts.task_contexts, start and goal far enough apart), seed 0."""
    if source == "sampled":
        from mpd.data.eval_contexts import sampled_contexts

        cs = sampled_contexts(task, n, extra_objects=False)
        return cs.q_start, cs.q_goal
    from mpd.data.dataset import SPLITS, load_dataset
    from mpd.data.eval_contexts import held_out_candidates

    ds = load_dataset(f"{task.name}-paper")
    if source == "held-out":
        c = held_out_candidates(task, ds, 0)
        return c["q_start"][:n], c["q_goal"][:n]
    if source == "task":  # the evaluations' contexts: held out, valid, at least min_start_goal_distance apart
        from mpd.data.eval_contexts import task_contexts

        cs = task_contexts(task, ds, n)
        return cs.q_start, cs.q_goal
    sel = np.flatnonzero((ds.split == SPLITS.index("train")) & ~ds.reversed)
    sel = np.random.default_rng(0).permutation(sel)[:n]
    return ds.q_start[sel], ds.q_goal[sel]


def run(
    task_name: str,
    n_contexts: int,
    n_samples: int,
    variants: list[str],
    source: str,
    model: str | None = None,
    method: str = "dprior",
    extra_objects: bool = False,
) -> pd.DataFrame:
    import mpd
    from mpd.envs.primitives import ObjectSet
    from mpd.tasks import load_task

    task = load_task(task_name)
    q_start, q_goal = contexts(task, n_contexts, source)
    index = np.arange(len(q_start))
    if extra_objects:  # the contexts valid with the extra objects, as an experiment's scene keeps them
        from mpd.data.eval_contexts import _ends_valid

        index = np.flatnonzero(_ends_valid(task, q_start, q_goal, True, 0.0))
    radius = float(task.robot.sphere_radii[0]) if hasattr(task.robot, "sphere_radii") else 0.02
    frames = []
    for name in variants:
        planner = mpd.load_planner(
            task_name, method, model=model, fast=False, extra_objects=extra_objects, **VARIANTS[name]
        )
        env = planner.scene()
        one_by_one = [ObjectSet(env.dim, [p], env.fixed.corner_radius) for p, _ in env.primitives]
        # a box as long as the workspace's half is a wall of the passage; the extra objects as such
        kinds = [
            "extra" if extra else "wall" if p.kind == "box" and max(p.half_size) > 0.4 else p.kind
            for p, extra in env.primitives
        ]
        t0 = time.perf_counter()
        for i in index:
            plan = planner.plan(q_start[i], q_goal[i], n_samples=n_samples, seed=int(i))
            q = torch.as_tensor(plan.q)  # (S, T, 2)
            d = env.sdf(q, mode="analytic") - radius
            worst = d.argmin(1)
            at = q[torch.arange(len(q)), worst]
            hit = torch.stack([o.sdf(at.double()) for o in one_by_one]).argmin(0).numpy()  # the nearest obstacle
            frames.append(
                pd.DataFrame(
                    {
                        "task": task_name,
                        "contexts": source,
                        "variant": name,
                        "method": method,
                        "scene": "extra-objects" if extra_objects else "training",
                        "model": f"{plan.provenance['model_identity']} ({plan.provenance['model_source']})",
                        "context": i,
                        "distance": float(np.linalg.norm(np.asarray(q_goal[i]) - np.asarray(q_start[i]))),
                        "valid": plan.valid,
                        "collision_free": plan.collision_free,
                        "limits_ok": plan.limits_ok,
                        "clearance": d.min(1).values.numpy(),
                        "obstacle": [kinds[h] for h in hit],
                    }
                )
            )
        print(f"{name:20s} {time.perf_counter() - t0:6.1f} s", flush=True)
    return pd.concat(frames, ignore_index=True)


def summary(df: pd.DataFrame) -> pd.DataFrame:
    rows = []
    df = _with_method(df)
    for (task, model, source, name, method, scene), g in df.groupby(
        ["task", "model", "contexts", "variant", "method", "scene"], sort=False
    ):
        bad = g[~g.collision_free]
        q = bad.clearance.quantile([0.1, 0.5, 0.9]) * 100 if len(bad) else pd.Series([np.nan] * 3)
        rows.append(
            {
                "task": task.split("-")[0],
                "model": model,
                "contexts": source,
                "variant": name,
                "method": method,
                "scene": scene,
                "fraction valid %": 100 * g.valid.mean(),
                "collision-free %": 100 * g.collision_free.mean(),
                "within limits %": 100 * g.limits_ok.mean(),
                "success %": 100 * g.groupby("context").valid.any().mean(),
                "colliding: clearance p10 / p50 / p90 cm": " / ".join(f"{v:.1f}" for v in q.values),
                "colliding: shallower than 1 cm %": 100 * (bad.clearance > -0.01).mean() if len(bad) else np.nan,
                **{
                    f"colliding: deepest in a {k} %": 100 * (bad.obstacle == k).mean() if len(bad) else np.nan
                    for k in ("wall", "sphere", "box", "extra")
                },
            }
        )
    return pd.DataFrame(rows)


def _with_method(df: pd.DataFrame) -> pd.DataFrame:
    """Files written before the method and scene columns: Dprior in the training scene."""
    return df.assign(**{k: v for k, v in (("method", "dprior"), ("scene", "training")) if k not in df})


def by_distance(df: pd.DataFrame, bins=(0.0, 0.5, 1.0, 1.4, 2.0, 3.0)) -> pd.DataFrame:
    """Fraction valid (%) by the contexts' start-goal distance, per context source and sampler variant."""
    d = _with_method(df).assign(distance=pd.cut(df.distance, list(bins)))
    d["task"] = d.task.str.split("-").str[0]
    keys = ["task", "model", "contexts", "variant", "method", "scene"]
    t = d.groupby([*keys, "distance"], observed=True).valid.mean().mul(100).round(1)
    order = d[keys].drop_duplicates().apply(tuple, axis=1).tolist()
    t = t.unstack("distance")
    return t.loc[[o for o in order if o in t.index]]


def main() -> None:
    torch.set_num_threads(1)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="EnvNarrowPassageDense2D-RobotPointMass2D")
    ap.add_argument("--contexts", type=int, default=50)
    ap.add_argument("--samples", type=int, default=100)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--contexts-from", default="sampled", choices=["sampled", "train", "held-out", "task"])
    ap.add_argument("--model", default=None, help="a model identity or checkpoint (default: the shipped prior)")
    ap.add_argument("--method", default="dprior", help="the planner (dprior, dprior-cost, mpd, ...)")
    ap.add_argument("--extra-objects", action="store_true", help="the task's scene with its extra objects")
    ap.add_argument("--out", type=Path, default=Path("/tmp/misses.parquet"))
    if sys.argv[1:2] == ["summary"]:
        df = pd.concat([pd.read_parquet(f) for f in sys.argv[2:]], ignore_index=True)
        pd.set_option("display.width", 250)
        pd.set_option("display.max_columns", 20)
        print(summary(df).round(1).to_string(index=False))
        print(by_distance(df).to_string())
        return
    args = ap.parse_args()
    df = run(
        args.task,
        args.contexts,
        args.samples,
        args.variants,
        args.contexts_from,
        args.model,
        args.method,
        args.extra_objects,
    )
    df.to_parquet(args.out)
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 20)
    print(summary(df).round(1).to_string(index=False))
    print(by_distance(df).to_string())


if __name__ == "__main__":
    main()
