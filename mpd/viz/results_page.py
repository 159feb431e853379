"""The paper's results against ours, on one page (``docs/RESULTS.md``, ``mpd report paper``).

From the committed reports' results tables (``reports/<name>/results.parquet``) alone: every number the paper's
text states (``paper_numbers.toml``) beside ours with its 95 % interval and a verdict, then the orderings the paper
claims between methods, each with the paired interval of the difference on the same contexts. A number comes from
the first report of :data:`PAPER_REPORTS` that has its cell. Deterministic: the same tables give the same page.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mpd import stats
from mpd.viz.report_data import EXTRA, TRAIN, main_slice, method_label, prepare, scaled, task_order, trained_models
from mpd.viz.report_tables import _num, markdown_table, paper_comparison, paper_numbers

# the reports that reproduce the paper's main results, most faithful first: a number or an ordering comes from the
# first one that has its cell (eval-2d-authors: the 2-D B-spline priors of the authors' recipe; eval-2d-cpu keeps the
# 2-D rows of the `cpu` priors, and the cells the other lacks)
PAPER_REPORTS = ("eval-panda-gpu-priors", "eval-2d-authors", "eval-2d-cpu", "eval-planar-cpu")
HARDWARE = "a time depends on the hardware (the paper: an RTX 3090 GPU; ours: a CPU)"


@dataclass(frozen=True)
class Ordering:
    """A claim of the paper that ``a`` beats ``b`` on ``metric`` (``higher``: higher is better) in ``scene``
    ("train" or "extra") of ``task`` (None: every task of the paper's reports); ``ref``: the index of the sentence
    in ``paper_numbers.toml`` that states it, or None for the adaptation claim."""

    task: str | None
    scene: str
    metric: str
    a: str
    b: str
    higher: bool
    ref: int | None = None


WAREHOUSE = "EnvWarehouse-RobotPanda"
# the sentence of each claim: the index of a number of paper_numbers.toml that comes from it
ORDERINGS = (
    Ordering(None, "extra", "fraction_valid", "mpd", "dprior-cost", True),
    Ordering(None, "extra", "fraction_valid", "dprior-cost", "dprior", True),
    Ordering(WAREHOUSE, "extra", "fraction_valid", "mpd", "dprior", True, ref=14),
    Ordering(WAREHOUSE, "extra", "vendi", "mpd", "dprior-cost", True, ref=16),
    Ordering(WAREHOUSE, "extra", "success", "mpd", "gp-cost", True, ref=18),
    Ordering(WAREHOUSE, "extra", "ee_ori_error_deg", "mpd", "dprior", False, ref=20),
    Ordering(WAREHOUSE, "train", "vendi", "dprior", "cvae", True, ref=2),
    Ordering(WAREHOUSE, "train", "ee_pos_error", "dprior", "cvae", False, ref=4),
    Ordering(WAREHOUSE, "train", "ee_ori_error_deg", "dprior", "cvae", False, ref=4),
)
# (scale, unit) of a difference as the page prints it
DIFF_UNITS = {
    "fraction_valid": (100.0, "pp"),
    "success": (100.0, "pp"),
    "vendi": (1.0, ""),
    "ee_pos_error": (100.0, "cm"),
    "ee_ori_error_deg": (1.0, "°"),
}
SCENES = {"train": TRAIN, "extra": EXTRA}


def _reports(root: Path) -> dict[str, pd.DataFrame]:
    """The prepared results table of each report of :data:`PAPER_REPORTS` that is committed under ``root``."""
    out = {}
    for name in PAPER_REPORTS:
        path = root / name / "results.parquet"
        if path.exists():
            out[name] = prepare(pd.read_parquet(path))
    return out


def _priors(root: Path, name: str, task: str) -> str:
    """The training profile of a report's priors for ``task``, and each model it trains otherwise (from its manifest's
    spec), e.g. "`cpu`; diffusion-bspline `paper-decay` 200,000 steps"."""
    spec = json.loads((root / name / "manifest.json").read_text()).get("spec", {})
    ts = spec.get("tasks", {}).get(task, {})
    return "; ".join([f"`{ts.get('profile', 'cpu')}`", *trained_models(ts)])


def _source(name: str, root: Path, task: str) -> str:
    return f"[{name}](../reports/{name}/) ({_priors(root, name, task)})"


def _kind(verdict: str) -> str:
    """A verdict without its reason: "outside (ours higher)" -> "outside"."""
    return verdict.split(" (")[0].split(":")[0]


def number_verdict(metric: str, paper: float, lo: float, hi: float) -> str:
    """inside / outside the interval (and on which side ours lies) / not comparable, and why."""
    if metric.startswith("time_"):
        return f"not comparable: {HARDWARE}"
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return "not comparable: too few contexts for an interval"
    if lo <= paper <= hi:
        return "inside"
    return "outside (ours higher)" if lo > paper else "outside (ours lower)"


def numbers_table(reports: dict[str, pd.DataFrame], root: Path) -> tuple[str, dict[str, int]]:
    """Every number the paper states, ours beside it from the first report that has the cell; and the counts of
    each verdict (inside / outside / not comparable)."""
    found: dict[int, tuple[str, pd.Series]] = {}
    for name, d in reports.items():
        t, _ = paper_comparison(d)
        for _, r in t.iterrows():
            found.setdefault(int(r["number"]), (name, r))
    rows, counts = [], {"inside": 0, "outside": 0, "not comparable": 0}
    for i, num in enumerate(paper_numbers()):
        unit = num.get("unit", "")
        unit = unit if unit in ("%", "°", "") else f" {unit}"
        scene = SCENES.get(num.get("scene", "any"), f"{TRAIN} (not stated)")
        head = [num["task"], scene, method_label(num["method"]), num["metric"], f"{num['value']}{unit}"]
        if i not in found:
            counts["not comparable"] += 1
            rows.append([*head, "–", "–", _ref(i), "not comparable: no committed report has this cell"])
            continue
        name, r = found[i]
        like = r["paper_text"]
        ours = _num(r["ours"], like)
        if np.isfinite(r["ours_lo"]):
            ours += f" [{_num(r['ours_lo'], like)}, {_num(r['ours_hi'], like)}]"
        verdict = number_verdict(num["metric"], float(num["value"]), r["ours_lo"], r["ours_hi"])
        counts[_kind(verdict)] += 1
        rows.append([*head, f"{ours}{unit} ({r['contexts']})", _source(name, root, num["task"]), _ref(i), verdict])
    header = ["task", "scene", "method", "metric", "paper", "ours [95 %] (contexts)", "ours from", "source", "verdict"]
    return markdown_table(header, rows, ["l", "l", "l", "l", "r", "r", "l", "l", "l"]), counts


def _paired(d: pd.DataFrame, o: Ordering, task: str) -> stats.Paired | None:
    """``a`` against ``b`` on the contexts both planned (the paper's setting of the variant axes)."""
    g, _ = main_slice(d[(d["task"] == task) & (d["scene"] == SCENES[o.scene])])
    if o.metric not in g.columns:
        return None
    key = ["seed", "context_index"]
    a = g[g["method"] == o.a].set_index(key)[o.metric]
    b = g[g["method"] == o.b].set_index(key)[o.metric]
    common = a.index.intersection(b.index)
    if a.empty or b.empty or len(common) == 0:
        return None
    x = pd.to_numeric(a.loc[common], errors="coerce").to_numpy(float)
    y = pd.to_numeric(b.loc[common], errors="coerce").to_numpy(float)
    return stats.paired(x, y, higher_is_better=o.higher)


def ordering_verdict(e: stats.Estimate, higher: bool) -> str:
    """holds (the interval excludes 0 in the claimed direction) / reversed / not resolved (it holds 0)."""
    if e.n < 2 or not (np.isfinite(e.lo) and np.isfinite(e.hi)):
        return "not comparable: too few contexts for an interval"
    lo, hi = (e.lo, e.hi) if higher else (-e.hi, -e.lo)
    if lo > 0:
        return "holds"
    if hi < 0:
        return "reversed"
    return "not resolved (the interval holds 0)"


def _ordering_tasks(reports: dict[str, pd.DataFrame], o: Ordering) -> list[tuple[str, str]]:
    """(task, report) pairs an ordering is checked on: its task, or every task, each from the first report that
    ran both methods there."""
    out: dict[str, str] = {}
    for name, d in reports.items():
        for task in task_order(d["task"].unique()):
            if o.task not in (None, task) or task in out:
                continue
            g = d[(d["task"] == task) & (d["scene"] == SCENES[o.scene])]
            if {o.a, o.b} <= set(g["method"]):
                out[task] = name
    return [(t, out[t]) for t in task_order(out)]


def orderings_table(reports: dict[str, pd.DataFrame], root: Path) -> tuple[str, dict[str, int]]:
    rows, counts = [], {"holds": 0, "reversed": 0, "not resolved": 0}  # a fixed order, whatever comes first
    for o in ORDERINGS:
        scale, unit = DIFF_UNITS[o.metric]
        for task, name in _ordering_tasks(reports, o):
            p = _paired(reports[name], o, task)
            if p is None:
                continue
            claim = f"{method_label(o.a)} {'>' if o.higher else '<'} {method_label(o.b)}"
            e = scaled(p.difference, scale)
            verdict = ordering_verdict(e, o.higher)
            kind = _kind(verdict)
            counts[kind] += 1
            diff = _fmt_diff(e, unit)
            src = "adaptation" if o.ref is None else _ref(o.ref)
            rows.append(
                [task, SCENES[o.scene], o.metric, claim, diff, str(e.n), _source(name, root, task), src, verdict]
            )
    header = ["task", "scene", "metric", "claim", "A − B [95 %]", "contexts", "ours from", "source", "verdict"]
    return markdown_table(header, rows, ["l", "l", "l", "l", "r", "r", "l", "l", "l"]), counts


def _sentences() -> list[str]:
    """The paper's sentences that state numbers, in order of first use (the page's references)."""
    return list(dict.fromkeys(num["sentence"] for num in paper_numbers()))


def _ref(number: int) -> str:
    """The reference of the sentence that states number ``number`` of ``paper_numbers.toml``."""
    return f"[{_sentences().index(paper_numbers()[number]['sentence']) + 1}]"


def _count_line(counts: dict[str, int], what: str) -> str:
    plural = {"holds": "hold"}
    return f"{what}: " + ", ".join(f"{n} {plural.get(k, k) if n > 1 else k}" for k, n in counts.items() if n)


def results_page(root: Path) -> str:
    """``docs/RESULTS.md`` from the committed reports under ``root`` (``reports/``)."""
    reports = _reports(root)
    numbers, n_counts = numbers_table(reports, root)
    orderings, o_counts = orderings_table(reports, root)
    refs = [f"[{i + 1}] “{s}”  " for i, s in enumerate(_sentences())]
    out = [
        "# The paper's results and ours",
        "",
        "Generated by `mpd report paper` from the committed reports' results tables (`reports/*/results.parquet`); "
        "a test fails when this page and the reports disagree. Ours: mean [95 % interval] over the contexts "
        "(bootstrap; Wilson's interval for success), from the first of "
        + ", ".join(f"[{n}](../reports/{n}/)" for n in PAPER_REPORTS)
        + " that has the cell; the profile of its priors in brackets (`gpu`: trained on a GPU, `cpu`: on a 2-core "
        "CPU, both far shorter than the paper's). How each number was matched to a cell: "
        "[`mpd/viz/paper_numbers.toml`](../mpd/viz/paper_numbers.toml).",
        "",
        f"**{_count_line(n_counts, 'The paper’s numbers')}. {_count_line(o_counts, 'Its orderings')}.**",
        "",
        "## The paper's numbers",
        "",
        "Verdict: whether the paper's number lies inside our 95 % interval. End-effector errors: each context's mean "
        "over its valid samples of the SE(3)-log errors (the position error is the translation part of "
        "log(T_goal T_ee⁻¹)), then the mean over contexts, which is the paper's definition; every other aggregate "
        "(the best sample, the Euclidean position error, medians) is beside it in the report's `paper.md` "
        "([evidence](../reports/ee-error-decomposition/README.md)).",
        "",
        numbers,
        "",
        "## The paper's orderings",
        "",
        "Each claim A > B (or A < B for an error) as the paired difference A − B on the same contexts (same start, "
        "goal and noise seed), mean [95 % bootstrap interval over the contexts]: **holds** when the interval "
        "excludes 0 in the claimed direction, **reversed** when it excludes 0 the other way. *adaptation*: the "
        "paper's central claim, checked on every task: with the extra objects MPD's samples are valid more often "
        "than those of the prior optimized after sampling, and those more often than the prior's "
        "(MPD > Dprior+Cost > Dprior).",
        "",
        orderings,
        "",
        "## Sources",
        "",
        *refs,
        "",
    ]
    return "\n".join(out)


GLANCE_START, GLANCE_END = "<!-- results: made by `mpd report paper` -->", "<!-- /results -->"


def _fmt_diff(e: stats.Estimate, unit: str) -> str:
    return f"{e.value:+.1f} [{e.lo:+.1f}, {e.hi:+.1f}]{(' ' + unit) if unit else ''}"


def glance(root: Path) -> str:
    """The README's results at a glance: the verdict counts of docs/RESULTS.md and the paper's adaptation claim per
    task (fraction valid with the extra objects, MPD > Dprior+Cost > Dprior, paired intervals)."""
    reports = _reports(root)
    _, n_counts = numbers_table(reports, root)
    _, o_counts = orderings_table(reports, root)
    rows = []
    for task, name in _ordering_tasks(reports, ORDERINGS[1]):
        cells = []
        for o in ORDERINGS[:2]:  # MPD > Dprior+Cost, Dprior+Cost > Dprior
            p = _paired(reports[name], o, task)
            e = None if p is None else scaled(p.difference, 100.0)
            cells.append("–" if e is None else f"{_fmt_diff(e, 'pp')}: {_kind(ordering_verdict(e, o.higher))}")
        rows.append([task, *cells, _priors(root, name, task)])
    table = markdown_table(["task", "MPD − Dprior+Cost", "Dprior+Cost − Dprior", "priors"], rows, ["l", "r", "r", "l"])
    return "\n".join(
        [
            GLANCE_START,
            f"**{_count_line(n_counts, 'The paper’s numbers')}. {_count_line(o_counts, 'Its orderings')}.**",
            "",
            "The paper's adaptation claim, fraction valid with the extra objects, MPD > Dprior+Cost > Dprior (paired "
            "difference on the same contexts, mean [95 % interval]):",
            "",
            table,
            GLANCE_END,
        ]
    )


def with_glance(readme: str, block: str, path: str = "README.md") -> str:
    """``readme`` with the text between the glance markers replaced by ``block``."""
    if GLANCE_START not in readme or GLANCE_END not in readme:
        raise ValueError(f"{path}: no {GLANCE_START} ... {GLANCE_END} block to fill")
    head, rest = readme.split(GLANCE_START, 1)
    return head + block + rest.split(GLANCE_END, 1)[1]


__all__ = [
    "ORDERINGS",
    "PAPER_REPORTS",
    "Ordering",
    "glance",
    "number_verdict",
    "ordering_verdict",
    "results_page",
    "with_glance",
]
