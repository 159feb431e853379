"""End-effector errors of EnvWarehouse-RobotPanda: which aggregate the paper's numbers are, and what moves ours.

Three subcommands (reports/ee-error-decomposition/README.md has the results):

* ``aggregates``: every aggregate of the committed results of a run (no planning): per context the mean over the
  valid samples (SE(3)-log translation and Euclidean position error) or the best valid sample, then the mean or the
  median over contexts, beside the paper's numbers.
* ``decompose``: plans the same contexts with the shipped prior for MPD and Dprior+Cost, changing one factor at a
  time (end-effector cost weight, guided / inner / optimization steps, gradient clipping, step size, the authors'
  first-order EE gradient, ...), and writes every sample's end-effector errors and validity; the table gives
  each variant's aggregates over all samples, the valid ones and the best one.
* ``cosine``: the cosine between the exact gradient of 1/2 |log(T_goal T_ee^-1)|^2 (what mpd steps along) and the
  authors' -J_s^T xi, in joint space, at the final configurations of Dprior samples.

Run with one thread (the machine is shared): ``OMP_NUM_THREADS=1 MPD_CACHE=/tmp/ee-cache python
benchmarks/tools/ee_decomposition.py decompose --contexts 20 --samples 100 --out /tmp/ee-decomp.parquet``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

TASK = "EnvWarehouse-RobotPanda"
PAPER = {  # the paper's EnvWarehouse numbers, training scene (cm, degrees)
    "cvae": (7.4, 10.5),
    "dprior": (5.2, 6.7),
    "dprior-cost": (2.00, 1.1),
    "mpd": (2.00, 1.1),
}

# (name, method, planner settings, cost weight overrides, ee gradient) -- one factor changed at a time
VARIANTS = [
    ("baseline", "mpd", {}, {}, "exact"),
    ("EE weight x10", "mpd", {}, {"ee_pose": 10.0}, "exact"),
    ("EE weight x100", "mpd", {}, {"ee_pose": 100.0}, "exact"),
    ("no gradient clip", "mpd", {"grad_clip": None}, {}, "exact"),
    ("guided steps 5 (fraction 0.3)", "mpd", {"guide_fraction": 0.3}, {}, "exact"),
    ("inner steps M 8", "mpd", {"n_inner_steps": 8}, {}, "exact"),
    ("guide lr gamma 2", "mpd", {"guide_lr": 2.0}, {}, "exact"),
    ("collision weight 0", "mpd", {}, {"collision": 0.0, "self_collision": 0.0}, "exact"),
    ("authors' EE gradient -J_s^T xi", "mpd", {}, {}, "authors"),
    ("DDIM eta 0", "mpd", {"eta": 0.0}, {}, "exact"),
    ("prior weight lambda 1", "mpd", {"prior_weight": 1.0}, {}, "exact"),
    ("baseline", "dprior-cost", {}, {}, "exact"),
    ("EE weight x10", "dprior-cost", {}, {"ee_pose": 10.0}, "exact"),
    ("EE weight x100", "dprior-cost", {}, {"ee_pose": 100.0}, "exact"),
    ("no gradient clip", "dprior-cost", {"opt_grad_clip": None}, {}, "exact"),
    ("opt steps 48", "dprior-cost", {"opt_steps": 48}, {}, "exact"),
    ("opt lr 0.1", "dprior-cost", {"opt_lr": 0.1}, {}, "exact"),
    ("collision weight 0", "dprior-cost", {}, {"collision": 0.0, "self_collision": 0.0}, "exact"),
    ("authors' EE gradient -J_s^T xi", "dprior-cost", {}, {}, "authors"),
    ("baseline", "dprior", {}, {}, "exact"),
]


# -- aggregates of committed results -------------------------------------------------------------------------------
def aggregates(results: Path) -> pd.DataFrame:
    d = pd.read_parquet(results)
    d = d[(d.task == TASK) & (~d.extra_objects.astype(bool)) & d.method.isin(list(PAPER))]
    cands = {
        "valid mean, log (mpd's ee_pos_error)": ("ee_pos_error", "ee_ori_error_deg"),
        "valid mean, Euclidean": ("ee_pos_error_euclidean", "ee_ori_error_deg"),
        "best valid sample, log": ("best_ee_pos_error", "best_ee_ori_error_deg"),
        "best valid sample, Euclidean": ("best_ee_pos_error_euclidean", "best_ee_ori_error_deg"),
    }
    rows = []
    for m, g in d.groupby("method"):
        for name, (p, o) in cands.items():
            for over, f in (("mean", np.nanmean), ("median", np.nanmedian)):
                rows.append(
                    {
                        "method": m,
                        "per context": name,
                        "over contexts": over,
                        "pos cm": 100 * f(g[p]),
                        "ori deg": f(g[o]),
                        "paper pos cm": PAPER[m][0],
                        "paper ori deg": PAPER[m][1],
                        "contexts": int(g[p].notna().sum()),
                    }
                )
    return pd.DataFrame(rows)


def carry_through(results: Path) -> pd.DataFrame:
    """Per context (same contexts, committed results): the cost-guided method's mean valid EE error against
    Dprior's: correlation, least-squares slope and intercept, and the paper's Dprior number times that slope."""
    d = pd.read_parquet(results)
    d = d[(d.task == TASK) & (~d.extra_objects.astype(bool))]
    rows = []
    for m in ("dprior-cost", "mpd"):
        for col, k, scale in (("ee_pos_error", 0, 100.0), ("ee_ori_error_deg", 1, 1.0)):
            p = d.pivot_table(index="context_index", columns="method", values=col)
            ok = p["dprior"].notna() & p[m].notna()
            x, y = scale * p.loc[ok, "dprior"], scale * p.loc[ok, m]
            slope, icpt = np.polyfit(x, y, 1)
            ratio = float((y / x).mean())
            rows.append(
                {
                    "method": m,
                    "metric": col,
                    "contexts": int(ok.sum()),
                    "r": float(np.corrcoef(x, y)[0, 1]),
                    "slope": float(slope),
                    "intercept": float(icpt),
                    "mean ratio to Dprior": ratio,
                    "paper's Dprior x ratio": PAPER["dprior"][k] * ratio,
                    "paper": PAPER[m][k],
                }
            )
    return pd.DataFrame(rows)


def sample_carry_through(samples: pd.DataFrame) -> pd.DataFrame:
    """Per sample (Dprior+Cost starts from the very samples of Dprior: same contexts and seeds): the error after
    the optimization against the error before it, by variant."""
    base = samples[(samples.method == "dprior") & (samples.variant == "baseline")].set_index(["context", "sample"])
    rows = []
    for v, g in samples[samples.method == "dprior-cost"].groupby("variant", sort=False):
        g = g.set_index(["context", "sample"])
        x, y = base.loc[g.index], g
        for col in ("pos_log", "ori_deg"):
            slope = float((x[col] * y[col]).sum() / (x[col] ** 2).sum())
            rows.append(
                {
                    "variant": v,
                    "error": col,
                    "r": float(np.corrcoef(x[col], y[col])[0, 1]),
                    "slope through 0": slope,
                    "median ratio after / before": float((y[col] / x[col]).median()),
                }
            )
    return pd.DataFrame(rows)


# -- planning ------------------------------------------------------------------------------------------------------
def _authors_ee_pose_error(preset, pos, rot, goal_pos, goal_rot):
    """The authors' step direction: -J_s^T xi, i.e. xi in place of the exact gradient of 1/2 |xi|^2."""
    from mpd.costs.se3 import cross, se3_log

    R = goal_rot @ rot.transpose(-1, -2)
    t = goal_pos - (R @ pos[..., None])[..., 0]
    xi, _ = se3_log(R, t)
    y = -xi
    y_v, y_w = y[..., :3], y[..., 3:]
    return 0.5 * xi.square().sum(-1), y_v, y_w - cross(pos, y_v)


def _contexts(n: int):
    from mpd.data.contexts import evaluation_contexts
    from mpd.tasks import load_task

    return evaluation_contexts(load_task(TASK), n)


def _planner(method: str, settings: dict, weights: dict, ee_grad: str):
    import mpd
    from mpd.costs import CostFunction
    from mpd.costs import ee_pose as ee_mod

    p = mpd.load_planner(TASK, method, fast=False, **settings)
    inner = p._planner
    if weights:
        inner.cost = CostFunction(
            inner.task, inner.param, inner.env, preset=inner.settings.cost_preset, weights=weights, profile=True
        )
    ee_mod.ee_pose_error = _authors_ee_pose_error if ee_grad == "authors" else _EXACT
    return inner


def _per_sample(task, checker, res, p_goal, r_goal) -> pd.DataFrame:
    from mpd.metrics import ee_pose_errors

    d = res.dense
    q = d.q.double()
    val = checker.trajectories(q, d.dq_dt.double(), d.ddq_dt2.double())
    p_end, r_end = task.robot.ee_pose(q[:, -1])
    pos, ori, euc = ee_pose_errors(p_end, r_end, p_goal, r_goal)
    return pd.DataFrame(
        {
            "sample": np.arange(q.shape[0]),
            "valid": val.valid.numpy(),
            "pos_log": pos.numpy(),
            "pos_euc": euc.numpy(),
            "ori_deg": ori.numpy(),
        }
    )


def decompose(n_contexts: int, n_samples: int, out: Path, only: str | None = None) -> pd.DataFrame:
    from mpd import kernels
    from mpd.collision import CollisionChecker
    from mpd.planners import Context
    from mpd.tasks import load_task

    task = load_task(TASK)
    cs = _contexts(n_contexts)
    checker = CollisionChecker(task)
    frames = [pd.read_parquet(out)] if out.exists() else []
    done = (
        {(r.method, r.variant) for r in frames[0][["method", "variant"]].drop_duplicates().itertuples()}
        if frames
        else set()
    )
    for name, method, settings, weights, ee_grad in VARIANTS:
        if (method, name) in done or (only and only not in f"{method} {name}"):
            continue
        planner = _planner(method, settings, weights, ee_grad)
        t0 = time.perf_counter()
        # the authors' EE gradient replaces the torch path's ee_pose_error: the EE cost then runs in torch
        with kernels.use("compiled" if ee_grad == "exact" else "torch", "ee_pose"):
            for i in range(len(cs)):
                f32 = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
                ctx = Context(
                    f32(cs.q_start[i]), None, f32(cs.ee_pos[i]), f32(cs.ee_rot[i]), q_goal_ref=f32(cs.q_goal[i])
                )
                res = planner.plan(ctx, n_samples, seed=i)
                df = _per_sample(task, checker, res, torch.as_tensor(cs.ee_pos[i]), torch.as_tensor(cs.ee_rot[i]))
                df.insert(0, "context", i)
                df.insert(0, "variant", name)
                df.insert(0, "method", method)
                frames.append(df)
        print(f"{method:12s} {name:34s} {time.perf_counter() - t0:6.1f} s", flush=True)
        pd.concat(frames, ignore_index=True).to_parquet(out)
    return pd.concat(frames, ignore_index=True)


def summarize(samples: pd.DataFrame) -> pd.DataFrame:
    """Per (method, variant): fraction valid and the EE errors over all samples, the valid ones, the best one."""
    rows = []
    for (m, v), g in samples.groupby(["method", "variant"], sort=False):
        per_ctx = []
        for _, c in g.groupby("context"):
            ok = c[c.valid]
            b = ok.loc[ok.pos_log.idxmin()] if len(ok) else None
            per_ctx.append(
                {
                    "all_pos": c.pos_log.mean(),
                    "all_ori": c.ori_deg.mean(),
                    "valid_pos": ok.pos_log.mean() if len(ok) else np.nan,
                    "valid_euc": ok.pos_euc.mean() if len(ok) else np.nan,
                    "valid_ori": ok.ori_deg.mean() if len(ok) else np.nan,
                    "best_pos": np.nan if b is None else b.pos_log,
                    "best_ori": np.nan if b is None else b.ori_deg,
                }
            )
        pc = pd.DataFrame(per_ctx)
        ok = g[g.valid]
        rows.append(
            {
                "method": m,
                "variant": v,
                "fraction valid %": 100 * g.valid.mean(),
                "all: pos cm / ori deg": f"{100 * pc.all_pos.mean():.2f} / {pc.all_ori.mean():.2f}",
                "valid: pos cm / ori deg": f"{100 * pc.valid_pos.mean():.2f} / {pc.valid_ori.mean():.2f}",
                "valid Euclidean cm": round(100 * pc.valid_euc.mean(), 2),
                "valid, median sample: pos cm / ori deg": (
                    f"{100 * ok.pos_log.median():.2f} / {ok.ori_deg.median():.2f}"
                ),
                "best: pos cm / ori deg": f"{100 * pc.best_pos.mean():.2f} / {pc.best_ori.mean():.2f}",
            }
        )
    return pd.DataFrame(rows)


def cosine(n_contexts: int, n_samples: int) -> pd.DataFrame:
    """Joint-space cosine between the exact gradient and the authors' -J_s^T xi at Dprior samples' final q."""
    from mpd.costs.base import CostInput
    from mpd.planners import Context
    from mpd.tasks import load_task

    task = load_task(TASK)
    cs = _contexts(n_contexts)
    planner = _planner("dprior", {}, {}, "exact")
    rows = []
    for i in range(len(cs)):
        f32 = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
        ctx = Context(f32(cs.q_start[i]), None, f32(cs.ee_pos[i]), f32(cs.ee_rot[i]), q_goal_ref=f32(cs.q_goal[i]))
        d = planner.plan(ctx, n_samples, seed=i).dense
        dense = type(d)(d.q.double(), d.dq_ds.double(), d.ddq_ds2.double(), d.duration)
        B = dense.q.shape[0]
        goal = (torch.as_tensor(cs.ee_pos[i]).expand(B, 3), torch.as_tensor(cs.ee_rot[i]).expand(B, 3, 3))
        kin = CostInput(dense, task, planner.env, goal, "nearest").last_kinematics()
        g = {}
        for k, fn in (("exact", _EXACT), ("authors", _authors_ee_pose_error)):
            value, gp, gr = fn("official", kin.ee_pos, kin.ee_rot, *goal)
            g[k] = task.robot.ee_vjp(kin, gp, gr)
        c = torch.nn.functional.cosine_similarity(g["exact"], g["authors"], dim=-1)
        rows.append(pd.DataFrame({"context": i, "cos": c.numpy(), "value": value.numpy()}))
    return pd.concat(rows, ignore_index=True)


def markdown(df: pd.DataFrame) -> str:
    """A pipe table (no tabulate dependency)."""
    fmt = lambda x: f"{x:.2f}" if isinstance(x, float) else str(x)  # noqa: E731
    lines = ["| " + " | ".join(df.columns) + " |", "|" + " --- |" * len(df.columns)]
    lines += ["| " + " | ".join(fmt(x) for x in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines)


def main() -> None:
    torch.set_num_threads(1)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("aggregates")
    a.add_argument("--results", type=Path, default=Path("reports/eval-panda-gpu-priors/results.parquet"))
    d = sub.add_parser("decompose")
    d.add_argument("--contexts", type=int, default=20)
    d.add_argument("--samples", type=int, default=100)
    d.add_argument("--out", type=Path, default=Path("/tmp/ee-decomp.parquet"))
    d.add_argument("--only", default=None, help="run only the variants whose 'method name' contains this")
    s = sub.add_parser("summary")
    s.add_argument("--samples-file", type=Path, default=Path("/tmp/ee-decomp.parquet"))
    c = sub.add_parser("cosine")
    c.add_argument("--contexts", type=int, default=20)
    c.add_argument("--samples", type=int, default=100)
    args = ap.parse_args()
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 20)
    if args.cmd == "aggregates":
        print(markdown(aggregates(args.results)))
        print()
        print(markdown(carry_through(args.results)))
    elif args.cmd == "decompose":
        print(markdown(summarize(decompose(args.contexts, args.samples, args.out, args.only))))
    elif args.cmd == "summary":
        samples = pd.read_parquet(args.samples_file)
        print(markdown(summarize(samples)))
        if {"dprior", "dprior-cost"} <= set(samples.method):
            print()
            print(markdown(sample_carry_through(samples)))
    else:
        c = cosine(args.contexts, args.samples)
        q = c.cos.quantile([0.0, 0.01, 0.05, 0.5]).round(4).to_dict()
        print(f"{len(c)} samples: cosine min / p1 / p5 / median = {q}, mean {c.cos.mean():.4f}")


from mpd.costs.ee_pose import ee_pose_error as _EXACT  # noqa: E402

if __name__ == "__main__":
    main()
