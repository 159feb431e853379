"""The results table prepared for the report: method labels and order, scene names, the slices a figure uses.

Everything here works on the results table alone (one row per (cell, context)), so a report can be rebuilt from
``results.parquet`` without the artifacts that produced it.
"""

from __future__ import annotations

import functools

import numpy as np
import pandas as pd

from mpd import stats
from mpd.experiments.tracking import AXIS_PREFIXES

TRAIN, EXTRA = "training environment", "extra objects"
# the axes of a cell besides task, method and scene; a figure that compares methods keeps one value of each
VARIANT_AXES = ("parametrization", "preset", "sampler", "n_samples", "overrides", "rotation_deg")
# preferred values of those axes (the paper's main setting) when a run has several
PREFERRED = {"parametrization": "bspline", "preset": "official", "n_samples": 100, "rotation_deg": 0.0, "overrides": ""}
BINARY = ("success",)  # 0 or 1 per context: Wilson's interval, not the bootstrap
# metrics of the summary table: (column, header, scale, format); scale turns fractions into % and m into cm
SUMMARY = (
    ("success", "success [%]", 100.0, "{:.1f}"),
    ("fraction_valid", "fraction valid [%]", 100.0, "{:.1f}"),
    ("vendi", "diversity (Vendi)", 1.0, "{:.2f}"),
    ("ee_pos_error", "EE pos. error [cm]", 100.0, "{:.2f}"),
    ("ee_ori_error_deg", "EE ori. error [°]", 1.0, "{:.2f}"),
    ("smoothness", "smoothness", 1.0, "{:.1f}"),
    ("path_length", "path length", 1.0, "{:.3f}"),
    ("time_total", "time [s]", 1.0, "{:.3f}"),
)


@functools.lru_cache(maxsize=1)
def _labels() -> dict[str, str]:
    from mpd.planners import PLANNERS

    return {name: cls.label or name for name, cls in PLANNERS.items()}


def method_label(method: str) -> str:
    return _labels().get(method, method)


@functools.lru_cache(maxsize=1)
def _order() -> tuple[str, ...]:
    from mpd.planners import METHOD_ORDER

    return tuple(METHOD_ORDER)


def method_order(methods) -> list[str]:
    """The paper's order (``METHOD_ORDER``), then any other method alphabetically."""
    order = _order()
    present = set(methods)
    return [m for m in order if m in present] + sorted(present - set(order))


def task_order(tasks) -> list[str]:
    """The tasks in the paper's order (``tests``' and the specs' order: 2-D first, then the Panda)."""
    paper = (
        "EnvSimple2D-RobotPointMass2D",
        "EnvNarrowPassageDense2D-RobotPointMass2D",
        "EnvPlanar2Link-RobotPlanar2Link",
        "EnvPlanar4Link-RobotPlanar4Link",
        "EnvSpheres3D-RobotPanda",
        "EnvWarehouse-RobotPanda",
    )
    present = set(tasks)
    return [t for t in paper if t in present] + sorted(present - set(paper))


@functools.lru_cache(maxsize=32)
def _task_has_ee_goal(task: str) -> bool | None:
    try:
        from mpd.tasks import load_task

        return load_task(task).ee_goal
    except Exception:  # a task file this checkout does not have: decided from the errors below
        return None


def ee_goal(d: pd.DataFrame, task: str) -> bool:
    """Whether ``task`` has an end-effector goal (its EE errors measure something); a joint-goal task's samples end
    on their goal by construction, and its EE columns do not apply (``–`` in the tables)."""
    known = _task_has_ee_goal(task)
    if known is not None:
        return known
    g = d[d["task"] == task]
    return bool("ee_pos_error" in g and (g["ee_pos_error"].abs() > 1e-9).any())


def applies(d: pd.DataFrame, task: str, metric: str) -> bool:
    """Whether ``metric`` means something on ``task``: the EE errors need an end-effector goal."""
    return not metric.startswith(("ee_", "best_ee_")) or ee_goal(d, task)


def trained_models(task_spec: dict) -> list[str]:
    """A spec task's models trained otherwise than its profile says, e.g. ["diffusion-bspline `paper-decay` 200,000
    steps"], in name order: how the results page and the reports index name a run's priors."""
    profile = task_spec.get("profile", "cpu")
    return [
        f"{model} `{m.get('profile') or profile}`" + (f" {m['train_steps']:,} steps" if m.get("train_steps") else "")
        for model, m in sorted((task_spec.get("models") or {}).items())
    ]


def short_task(task: str) -> str:
    """``EnvSpheres3D-RobotPanda`` -> ``Spheres3D / Panda``: short enough for a panel title."""
    env, _, robot = task.partition("-")
    return f"{env.removeprefix('Env')} / {robot.removeprefix('Robot')}" if robot else task


def prepare(df: pd.DataFrame) -> pd.DataFrame:
    """A copy with the columns every figure relies on: defaults for axes a run lacks, ``scene``, ``label``."""
    d = df.copy()
    defaults = {
        "extra_objects": False,
        "rotation_deg": 0.0,
        "parametrization": "bspline",
        "preset": "official",
        "sampler": None,
        "n_samples": 0,
        "overrides": "",
        "seed": 0,
        "context_index": 0,
    }
    for k, v in defaults.items():
        if k not in d.columns:
            d[k] = v
    d["extra_objects"] = d["extra_objects"].fillna(False).astype(bool)
    d["rotation_deg"] = d["rotation_deg"].fillna(0.0).astype(float)
    d["overrides"] = d["overrides"].fillna("").astype(str)
    d["parametrization"] = d["parametrization"].fillna("bspline").astype(str)
    d["scene"] = np.where(d["extra_objects"], EXTRA, TRAIN)
    d["label"] = [method_label(m) for m in d["method"]]
    for c in d.columns:  # infinite times / errors would break means and KDEs
        if d[c].dtype.kind == "f":
            d[c] = d[c].replace([np.inf, -np.inf], np.nan)
    return d


def _pick(values: pd.Series, preferred) -> object:
    """The preferred value when present, else the most frequent (ties: the smallest, for determinism)."""
    present = values.dropna()
    if preferred is not None and (present == preferred).any():
        return preferred
    if present.empty:
        return None
    counts = present.astype(str).value_counts()
    best = sorted(counts[counts == counts.max()].index)[0]
    return present[present.astype(str) == best].iloc[0]


def main_slice(d: pd.DataFrame, free: tuple[str, ...] = ()) -> tuple[pd.DataFrame, dict[str, object]]:
    """Rows of one setting of the variant axes (the paper's where present), per (task, method): a figure comparing
    methods then compares like with like. ``free`` axes are left as they are. Returns (rows, chosen values). Each
    axis is picked among the rows the axes before it kept, so a spec whose excludes tie axes together (e.g. two
    settings varied in pairs) still gets one of its own cells, never an empty combination."""
    keep = pd.Series(True, index=d.index)
    chosen: dict[str, object] = {}
    axes = [a for a in VARIANT_AXES if a not in free and a in d.columns]
    axes += sorted(c for c in d.columns if c.startswith(AXIS_PREFIXES) and c not in free)
    for axis in axes:
        for _, g in d[keep].groupby(["task", "method"], sort=True):
            col = g[axis]
            if col.isna().all() or col.astype(str).nunique() <= 1:
                continue
            v = _pick(col, PREFERRED.get(axis))
            keep.loc[g.index] &= col.astype(str) == str(v)
            chosen[axis] = v
    return d[keep], chosen


def describe_slice(chosen: dict[str, object]) -> str:
    return ", ".join(f"{k} = {v}" for k, v in sorted(chosen.items()))


def mean_std(x: pd.Series, scale: float = 1.0, fmt: str = "{:.3g}") -> str:
    x = pd.to_numeric(x, errors="coerce").dropna() * scale
    if x.empty:
        return "–"
    if len(x) == 1:
        return fmt.format(x.iloc[0])
    return f"{fmt.format(x.mean())} ± {fmt.format(x.std(ddof=1))}"


def scaled(e: stats.Estimate, scale: float) -> stats.Estimate:
    return stats.Estimate(e.value * scale, e.lo * scale, e.hi * scale, e.n)


def interval(x, scale: float = 1.0, binary: bool = False) -> stats.Estimate:
    return scaled(stats.mean_interval(pd.to_numeric(pd.Series(x), errors="coerce"), binary=binary), scale)


NOT_APPLICABLE = "–"  # a metric that does not apply (the EE errors of a joint-goal task) or has no value


def fmt_estimate(e: stats.Estimate, fmt: str = "{:.3g}", bold_if_excludes_zero: bool = False) -> str:
    """``value [lo, hi]``; the value alone with one context; ``–`` with none."""
    if e.n == 0 or not np.isfinite(e.value):
        return "–"
    if not (np.isfinite(e.lo) and np.isfinite(e.hi)):
        return fmt.format(e.value)
    text = f"{fmt.format(e.value)} [{fmt.format(e.lo)}, {fmt.format(e.hi)}]"
    return f"**{text}**" if bold_if_excludes_zero and e.excludes(0.0) else text


def mean_ci(x, scale: float = 1.0, fmt: str = "{:.3g}", binary: bool = False) -> str:
    return fmt_estimate(interval(x, scale, binary), fmt)
