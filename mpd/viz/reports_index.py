"""The index of the committed reports (``reports/README.md``, ``mpd report index``).

Per report folder: the question it answers (its spec's description), its spec, the training profile of its priors,
the date its run finished, a headline number from its results table, and the later report that supersedes it (a
``NAME-cpu`` report is superseded by its ``NAME-gpu-priors`` twin, the same spec with the priors trained on a GPU, or
else by its ``NAME-authors`` twin, the same spec with priors of the authors' recipe).
The paper's results, the superseded reports, the recipe studies and the probes are listed apart. Everything comes
from each folder's manifest and results table (or, for a benchmark's folder without a run, its README's title), so
the same folders give the same page.
"""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime
from pathlib import Path

import pandas as pd

from mpd.viz.report_data import EXTRA, TRAIN, interval, main_slice, method_label, prepare, task_order, trained_models
from mpd.viz.report_tables import markdown_table

RECIPE_STUDIES = ("recipe-study-", "priors-cpu", "guidance-sweep-", "guidance-form-")
PROBES = ("authors-check-panda", "compile-2d", "precision-2d", "quick")
GROUPS = {
    "paper": (
        "The paper's results",
        "The paper's experiments at this project's scale; how they compare with the paper's numbers: "
        "[docs/RESULTS.md](../docs/RESULTS.md).",
    ),
    "superseded": ("Superseded", "Kept for comparison: a later report answers the same question with better priors."),
    "recipes": (
        "Recipe and settings studies",
        "How the priors were trained and MPD's settings chosen: learning curves and the settings tried (headline: "
        "the best one).",
    ),
    "probes": ("Probes", "Checks that a fast path or the demo gives the same numbers as the reference."),
}


def _group(name: str, folders: set[str]) -> str:
    if superseded_by(name, folders):
        return "superseded"
    if name.startswith(RECIPE_STUDIES):
        return "recipes"
    if name in PROBES:
        return "probes"
    return "paper"


def superseded_by(name: str, folders: set[str]) -> str | None:
    """The report that supersedes ``name`` when it ends in ``-cpu``: its ``-gpu-priors`` twin, else its ``-authors``
    twin (the same spec with priors of the authors' recipe)."""
    if not name.endswith("-cpu"):
        return None
    twins = (name.removesuffix("-cpu") + suffix for suffix in ("-gpu-priors", "-authors"))
    return next((t for t in twins if t in folders), None)


def _link(folder: Path) -> str:
    page = "README.md" if (folder / "README.md").exists() else "report/index.md"
    return f"[{folder.name}]({folder.name}/{page})"


def _priors(spec: dict) -> str:
    """The training profiles of a run's models, e.g. "`gpu` (CVAE `cpu`)"."""
    tasks = spec.get("tasks", {}).values()
    profiles = sorted({t.get("profile", "cpu") for t in tasks})
    cvae = sorted({t["cvae_profile"] for t in tasks if t.get("cvae_profile")} - set(profiles))
    text = ", ".join(f"`{p}`" for p in profiles)
    text += f" (CVAE {', '.join(f'`{p}`' for p in cvae)})" if cvae else ""
    own = sorted({name for t in tasks for name in trained_models(t)})
    return text + (f"; {', '.join(own)}" if own else "")


def _pct(x: pd.Series, binary: bool = False) -> str:
    e = interval(x, 100.0, binary=binary)
    return f"{e.value:.1f} %" + (f" [{e.lo:.1f}, {e.hi:.1f}]" if e.n > 1 else "")


def headline(d: pd.DataFrame, studied: tuple[str, ...] = ("training.", "model.")) -> str:
    """MPD's (else Dprior's, else the first method's) fraction valid with its interval, success and time per plan,
    on the run's last task in the paper's order, with the extra objects where it ran them; where axes with a prefix
    of ``studied`` vary (a study of settings), of the best setting by fraction valid."""
    methods = list(d["method"].unique())
    method = next((m for m in ("mpd", "dprior") if m in methods), sorted(methods)[0])
    task = task_order(d["task"].unique())[-1]
    g = d[(d["task"] == task) & (d["method"] == method)]
    scene = EXTRA if (g["scene"] == EXTRA).any() else TRAIN
    g = g[g["scene"] == scene]
    recipe = sorted(c for c in g.columns if c.startswith(studied) and g[c].astype(str).nunique() > 1)
    label = ""
    if recipe:
        best = g.groupby(recipe, dropna=False)["fraction_valid"].mean().idxmax()
        best = best if isinstance(best, tuple) else (best,)
        for c, v in zip(recipe, best):
            g = g[g[c].astype(str) == str(v)]
        label = "best: " + ", ".join(f"{c.split('.', 1)[1]}={v}" for c, v in zip(recipe, best)) + "; "
    else:
        g, _ = main_slice(g)
    time = pd.to_numeric(g["time_total"], errors="coerce").mean()
    return (
        f"{method_label(method)} {_pct(g['fraction_valid'])} valid, {_pct(g['success'], True)} success, "
        f"{time:.2f} s a plan ({label}{task}, {scene}, {len(g)} contexts)"
    )


def _row(folder: Path, folders: set[str], group: str) -> list[str]:
    man_path = folder / "manifest.json"
    later = superseded_by(folder.name, folders)
    status = f"superseded by [{later}]({later}/README.md)" if later else "current"
    if not man_path.exists():  # a benchmark's folder: its README says what and when
        title = (folder / "README.md").read_text().splitlines()[0].lstrip("# ")
        date = re.search(r"\((\d{4}-\d{2}-\d{2})\)", title)
        question = title.split(": ", 1)[-1].split(" (")[0]
        return [_link(folder), question, "a benchmark", "–", date.group(1) if date else "–", "see its README", status]
    man = json.loads(man_path.read_text())
    spec = man.get("spec", {})
    name = man.get("spec_name", spec.get("name", folder.name))
    spec_file = Path(__file__).resolve().parents[2] / "benchmarks" / "specs" / f"{name}.toml"
    spec_text = f"[{name}](../benchmarks/specs/{name}.toml)" if spec_file.exists() else name
    date = datetime.fromtimestamp(man["finished_at"], UTC).strftime("%Y-%m-%d") if man.get("finished_at") else "–"
    d = prepare(pd.read_parquet(folder / "results.parquet"))
    studied = ("training.", "model.", "planner.") if group == "recipes" else ("training.", "model.")
    return [_link(folder), spec.get("description", ""), spec_text, _priors(spec), date, headline(d, studied), status]


def reports_index(root: Path) -> str:
    """``reports/README.md`` for the report folders under ``root``."""
    folders = sorted(p for p in root.iterdir() if (p / "results.parquet").exists() or (p / "README.md").exists())
    names = {p.name for p in folders}
    out = [
        "# Reports",
        "",
        "Generated by `mpd report index` from each folder's manifest and results table; a test fails when this page "
        "and the folders disagree. Each folder holds a run's results table (`results.parquet`), its manifest "
        "(spec, commit, versions) and its report (`report/index.md`); `mpd report reports/NAME` rebuilds the "
        "report, `mpd run SPEC` reruns it. Headline: mean [95 % interval] over the contexts.",
        "",
    ]
    header = ["report", "question", "spec", "priors", "date", "headline", "status"]
    for key, (title, note) in GROUPS.items():
        rows = [_row(p, names, key) for p in folders if _group(p.name, names) == key]
        if rows:
            out += [f"## {title}", "", note, "", markdown_table(header, rows), ""]
    return "\n".join(out)


__all__ = ["headline", "reports_index", "superseded_by"]
