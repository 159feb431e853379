"""Run tracking: list runs, summarise one, compare two (did this change move the numbers?), and optionally mirror
a run into a local MLflow store (the Parquet results stay the source of truth)."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from mpd.experiments.results import read_results
from mpd.paths import runs_dir

# the parameter columns that identify a cell, and the metrics compared between runs
CELL_COLUMNS = (
    "task",
    "method",
    "parametrization",
    "preset",
    "sampler",
    "extra_objects",
    "rotation_deg",
    "n_samples",
    "seed",
    "overrides",
)
SUMMARY_METRICS = (
    "success",
    "fraction_valid",
    "vendi",
    "ee_pos_error",
    "ee_ori_error_deg",
    "smoothness",
    "path_length",
    "time_total",
)
INPUT_HASHES = ("task_hash", "dataset_hash", "model_hash")


def list_runs() -> pd.DataFrame:
    rows = []
    for d in sorted(runs_dir().iterdir()):
        m = d / "manifest.json"
        if not m.exists():
            continue
        man = json.loads(m.read_text())
        rows.append(
            {
                "run": d.name,
                "spec": man.get("spec_name"),
                "status": man.get("status"),
                "cells": len(man.get("cells", [])),
                "rows": man.get("n_rows", 0),
                "commit": man.get("provenance", {}).get("git_commit", "")[:8],
                "started": pd.to_datetime(man.get("started_at", 0), unit="s").strftime("%Y-%m-%d %H:%M"),
            }
        )
    return pd.DataFrame(rows)


AXIS_PREFIXES = ("planner.", "training.", "model.")


def cell_columns(df: pd.DataFrame) -> list[str]:
    """The columns that name a cell: CELL_COLUMNS and the spec's planner.* / training.* / model.* axes."""
    return [c for c in CELL_COLUMNS if c in df.columns] + sorted(c for c in df.columns if c.startswith(AXIS_PREFIXES))


def _key(v) -> str:
    """A cell parameter as text; missing values (None/NaN: an axis a method does not use) as ''."""
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) or v is pd.NA else str(v)


def cell_summary(df: pd.DataFrame) -> pd.DataFrame:
    """Mean of the summary metrics per cell (over contexts)."""
    cols = cell_columns(df)
    mets = [m for m in SUMMARY_METRICS if m in df.columns]
    g = df.copy()
    for c in cols:
        g[c] = g[c].map(_key).astype(object)
    out = g.groupby(cols, dropna=False)[mets].mean()
    out["contexts"] = g.groupby(cols, dropna=False).size()
    return out.reset_index()


def show_run(run_dir: Path) -> str:
    man = json.loads((Path(run_dir) / "manifest.json").read_text())
    df = read_results(run_dir)
    prov = man.get("provenance", {})
    lines = [
        f"run {man['run_id']}  spec {man['spec_name']} ({man['spec_hash']})  status {man['status']}",
        f"commit {prov.get('git_commit', '?')[:12]}{' (dirty)' if prov.get('git_dirty') else ''}"
        f"  device {man.get('device')}",
        f"rows {len(df)}  cells {len(man.get('cells', []))}",
    ]
    for task, a in (man.get("artifacts") or {}).items():
        lines.append(
            f"  {task}: dataset {a.get('dataset_id')} ({a.get('dataset_hash', '')[:12]}), models {a.get('models')}"
        )
    if len(df):
        with pd.option_context("display.width", 200, "display.max_columns", 20, "display.max_rows", 200):
            lines.append(cell_summary(df).to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    return "\n".join(lines)


def compare_runs(run_a: Path, run_b: Path, tol: float = 0.0) -> tuple[pd.DataFrame, list[str]]:
    """Per-cell metric differences (B - A) and flags where the cells' inputs (task, dataset, model hashes) differ.

    Returns (table, notes); a cell present in only one run is listed with NaN differences.
    """
    a, b = read_results(run_a), read_results(run_b)
    keys = [c for c in CELL_COLUMNS if c in a.columns and c in b.columns]
    notes = []
    sa, sb = cell_summary(a), cell_summary(b)
    m = sa.merge(sb, on=keys, how="outer", suffixes=("_a", "_b"), indicator=True)
    rows = []
    for _, r in m.iterrows():
        row = {k: r[k] for k in keys}
        for met in SUMMARY_METRICS:
            if f"{met}_a" in r and met != "time_total":
                va, vb = r[f"{met}_a"], r[f"{met}_b"]
                row[f"d_{met}"] = vb - va if not (pd.isna(va) and pd.isna(vb)) else 0.0
        row["only_in"] = {"left_only": "A", "right_only": "B"}.get(str(r["_merge"]), "")
        rows.append(row)
    table = pd.DataFrame(rows)
    # input hashes per cell
    flags = []
    for _, r in table.iterrows():
        ha, hb = (df[np.logical_and.reduce([df[k].map(_key) == _key(r[k]) for k in keys])] for df in (a, b))
        changed = [
            h
            for h in INPUT_HASHES
            if h in a and h in b and len(ha) and len(hb) and set(ha[h].astype(str)) != set(hb[h].astype(str))
        ]
        flags.append(",".join(changed))
    table["inputs_changed"] = flags
    dcols = [c for c in table.columns if c.startswith("d_")]
    moved = table[dcols].abs().fillna(0).gt(tol).any(axis=1)
    table["moved"] = moved
    if not moved.any():
        notes.append("no metric difference")
    else:
        notes.append(f"{int(moved.sum())} of {len(table)} cells moved")
    if table["inputs_changed"].astype(bool).any():
        notes.append("inputs differ in some cells (see inputs_changed): the difference may come from them")
    return table, notes


def _mlflow_experiment(mlflow, tracking_uri: str | None) -> str:
    warnings.filterwarnings("ignore", message=".*noload.*")
    mlflow.set_tracking_uri(tracking_uri or f"sqlite:///{runs_dir() / 'mlflow.db'}")
    exp = mlflow.get_experiment_by_name("mpd")
    if exp:
        return exp.experiment_id
    return mlflow.create_experiment("mpd", artifact_location=(runs_dir() / "mlflow-artifacts").as_uri())


def log_model_to_mlflow(meta_path: Path, tracking_uri: str | None = None) -> str | None:
    """Mirror a trained model's training record (settings, loss curves, meta.json) into the local MLflow store,
    once per model identity."""
    try:
        import mlflow
    except ImportError:
        warnings.warn("mlflow is not installed (pip install -e .[mlflow]); skipping MLflow logging", stacklevel=2)
        return None
    meta = json.loads(Path(meta_path).read_text())
    exp_id = _mlflow_experiment(mlflow, tracking_uri)
    name = f"train-{meta['task_name']}-{meta['kind']}-{meta['parametrization']}-{meta['identity']}"
    if mlflow.search_runs(experiment_ids=[exp_id], filter_string=f"run_name = '{name}'", output_format="list"):
        return None
    with mlflow.start_run(experiment_id=exp_id, run_name=name) as r:
        ts = meta.get("training_spec", {})
        mlflow.log_params(
            {
                "task": meta["task_name"],
                "kind": meta["kind"],
                "parametrization": meta["parametrization"],
                "identity": meta["identity"],
                "dataset_hash": meta["dataset_hash"],
                "seed": meta.get("seed"),
                **{f"train.{k}": v for k, v in ts.items()},
            }
        )
        for h in meta.get("history", []):
            step = int(h.get("step", 0))
            for k in ("train_loss", "val_loss"):
                if h.get(k) is not None:
                    mlflow.log_metric(k, float(h[k]), step=step)
        for k in ("final_train_loss", "final_val_loss", "steps_per_s", "wall_time_s"):
            if meta.get(k) is not None:
                mlflow.log_metric(k, float(meta[k]))
        mlflow.log_artifact(str(meta_path))
        return r.info.run_id


def log_run_to_mlflow(run_dir: Path, tracking_uri: str | None = None) -> str | None:
    """Mirror a run into a local MLflow store (``sqlite:///<runs>/mlflow.db``): params, per-cell mean metrics and
    the results/manifest as artifacts. Returns the MLflow run id, or None when mlflow is not installed."""
    try:
        import mlflow
    except ImportError:
        warnings.warn("mlflow is not installed (pip install -e .[mlflow]); skipping MLflow logging", stacklevel=2)
        return None
    run_dir = Path(run_dir)
    man = json.loads((run_dir / "manifest.json").read_text())
    exp_id = _mlflow_experiment(mlflow, tracking_uri)
    df = read_results(run_dir)
    with mlflow.start_run(experiment_id=exp_id, run_name=man["run_id"]) as r:
        prov = man.get("provenance", {})
        mlflow.log_params(
            {
                "spec": man["spec_name"],
                "spec_hash": man["spec_hash"],
                "git_commit": prov.get("git_commit"),
                "cells": len(man.get("cells", [])),
                "device": man.get("device"),
            }
        )
        if len(df):
            summ = cell_summary(df)
            for _, row in summ.iterrows():
                tag = "/".join(str(row[c]) for c in ("task", "method", "extra_objects") if c in row)
                for met in SUMMARY_METRICS:
                    if met in row and not (isinstance(row[met], float) and math.isnan(row[met])):
                        mlflow.log_metric(_mlflow_key(f"{met}/{tag}"), float(row[met]))
        for f in ("results.parquet", "manifest.json"):
            if (run_dir / f).exists():
                mlflow.log_artifact(str(run_dir / f))
        return r.info.run_id


def _mlflow_key(s: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "_-./ " else "_" for ch in s)[:250]
