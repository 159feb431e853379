"""Reports from a synthetic results table: every figure kind is produced and is a non-empty image, the paper's
numbers sit beside ours, and building twice gives the same Markdown."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mpd.viz import report_figures as rf
from mpd.viz.report import build_report
from mpd.viz.report_data import EXTRA, TRAIN, main_slice, method_label, prepare
from mpd.viz.report_tables import paper_comparison, paper_numbers, paper_table

PNG = b"\x89PNG\r\n\x1a\n"
ROOT = Path(__file__).resolve().parents[1]
SIMPLE, WAREHOUSE, SPHERES = "EnvSimple2D-RobotPointMass2D", "EnvWarehouse-RobotPanda", "EnvSpheres3D-RobotPanda"
METHODS = ("gp-cost", "cvae", "cvae-cost", "dprior", "dprior-cost", "mpd", "rrtconnect-cost")
COSTS = ("acceleration", "chain_rule", "collision", "dense", "fk", "joint_limits", "velocity")


def _rows(rng, task, method, n_ctx, *, extra=False, rot=0.0, n=100, param="bspline", quality=0.8):
    """n_ctx rows of one cell with plausible metrics and timings."""
    ee = task != SIMPLE
    key = f"{task[:6]}-{method}-{int(extra)}-{rot:g}-{n}-{param}"
    out = []
    for i in range(n_ctx):
        q = float(np.clip(quality - 0.25 * extra + rng.normal(0, 0.12), 0.0, 1.0))
        grad = 0.0 if method in ("cvae", "dprior") else 0.3 + 0.05 * rng.random()
        net = 0.0 if method in ("gp-cost", "rrtconnect-cost") else 0.05 + 0.01 * rng.random() + 1e-4 * n
        sampling = net + 0.005
        costs = {f"time_cost_{c}": grad * w for c, w in zip(COSTS, (0.1, 0.1, 0.35, 0.05, 0.3, 0.02, 0.08))}
        out.append(
            {
                "cell_key": key,
                "context_index": i,
                "task": task,
                "method": method,
                "parametrization": param,
                "preset": "official",
                "sampler": "ddim" if method in ("mpd", "dprior", "dprior-cost") else None,
                "extra_objects": extra,
                "rotation_deg": rot,
                "n_samples": n,
                "seed": 0,
                "overrides": "",
                "success": float(rng.random() < q + 0.15),
                "fraction_valid": q,
                "n_valid": q * n,
                "vendi": 1 + q * n * 0.6 * rng.random(),
                "ee_pos_error": (0.02 + 0.05 * rng.random()) if ee else 0.0,
                "ee_ori_error_deg": (1 + 8 * rng.random()) if ee else 0.0,
                "smoothness": (40 if param == "bspline" else 160) * (1 + 0.3 * rng.random()),
                "path_length": 2 + rng.random(),
                "best_path_length": 1.5 + 0.5 * rng.random() + (0.4 if method == "rrtconnect-cost" else 0.0),
                "time_total": sampling + grad + 0.01 + (1.5 if method == "rrtconnect-cost" else 0.0),
                "time_sampling": sampling if net else np.nan,
                "time_network": net if net else np.nan,
                "time_cost_gradient": grad if grad else np.nan,
                **({k: v for k, v in costs.items()} if grad else {k: np.nan for k in costs}),
                "n_cost_gradient_calls": 20.0 if grad else np.nan,
                "run_id": "synthetic-0123abcd-89abcdef",
                "spec_name": "synthetic",
                "spec_hash": "0123abcd4567",
                "git_commit": "89abcdef" * 5,
                "git_dirty": False,
                "task_hash": f"{task}-hash",
                "dataset_id": "ds01",
                "dataset_hash": f"{task}-data",
                "model_hash": "" if method in ("gp-cost", "rrtconnect-cost") else f"{method}-model",
                "device": "cpu",
                "libraries": "python=3.11,torch=2.13.0+cpu",
            }
        )
    return out


def synthetic_results(n_ctx: int = 5, seed: int = 0, small: bool = False) -> pd.DataFrame:
    """Cells for every figure kind: Fig. 6 (two tasks x all methods x both scenes), rotation, batch sizes with
    RRTConnect+Cost (Fig. 10), B-spline vs waypoints. ``small``: every kind on the 2-D task with three methods
    (cheap to draw)."""
    rng = np.random.default_rng(seed)
    rows = []
    tasks, methods = ((SIMPLE,), ("gp-cost", "mpd", "rrtconnect-cost")) if small else ((SIMPLE, WAREHOUSE), METHODS)
    sweep = SIMPLE if small else WAREHOUSE
    batch = SIMPLE if small else SPHERES
    for task in tasks:
        for m in methods:
            for extra in (False, True):
                rows += _rows(rng, task, m, n_ctx, extra=extra, quality=0.4 + 0.08 * METHODS.index(m))
    for m in ("gp-cost", "mpd"):
        for rot in (10.0, 20.0):
            rows += _rows(rng, sweep, m, n_ctx, rot=rot, quality=0.7 - rot / 60)
    for n in (1, 10) if small else (1, 10, 100):
        rows += _rows(rng, batch, "mpd", n_ctx, extra=True, n=n, quality=0.5 + n / 300)
    if not small:
        rows += _rows(rng, batch, "rrtconnect-cost", n_ctx, extra=True, n=1, quality=0.6)
    rows += _rows(rng, SIMPLE, "mpd", n_ctx, extra=True, param="waypoints")
    for steps in (3000, 6000):  # a learning curve: Dprior at two training budgets (training.* axes)
        for r in _rows(rng, SIMPLE, "dprior", n_ctx, quality=0.3 + steps / 20000):
            r.update({"cell_key": f"{r['cell_key']}-{steps}", "training.steps": steps, "model_train_s": steps / 10.0})
            rows.append(r)
    return pd.DataFrame(rows)


def make_run(tmp: Path, n_ctx: int = 5, histories: bool = True, small: bool = False) -> Path:
    """A run folder with the synthetic table, a manifest and (optionally) one recorded MPD context per scene."""
    from test_recording import fake_history

    run = tmp / "synthetic-0123abcd-89abcdef"
    run.mkdir(parents=True)
    df = synthetic_results(n_ctx, small=small)
    df.to_parquet(run / "results.parquet", index=False)
    cells = df.drop_duplicates("cell_key")
    axes = [
        "task",
        "method",
        "parametrization",
        "preset",
        "sampler",
        "extra_objects",
        "rotation_deg",
        "n_samples",
        "seed",
    ]
    manifest = {
        "run_id": run.name,
        "spec_name": "synthetic",
        "spec_hash": "0123abcd4567",
        "spec_path": "tests/synthetic.toml",
        "spec": {"name": "synthetic", "description": "every figure kind, synthetic numbers"},
        "cells": [{"key": r["cell_key"], **{a: r[a] for a in axes}} for _, r in cells.iterrows()],
        "executor": "local",
        "workers": 1,
        "device": "cpu",
        "provenance": {"git_commit": "89abcdef" * 5, "git_dirty": False, "libraries": {"torch": "2.13.0+cpu"}},
        "started_at": 1_700_000_000.0,
        "finished_at": 1_700_000_100.0,
        "status": "completed",
        "artifacts": {SIMPLE: {"task_hash": "abc", "dataset_id": "ds01", "dataset_hash": "def", "models": {}}},
    }
    (run / "manifest.json").write_text(json.dumps(manifest, default=lambda x: x.item()))
    if histories:
        (run / "histories").mkdir()
        for extra in (False,) if small else (False, True):
            key = cells[
                (cells.task == SIMPLE)
                & (cells.method == "mpd")
                & (cells.extra_objects == extra)
                & (cells.parametrization == "bspline")
            ]["cell_key"].iloc[0]
            row = {
                "cell_key": key,
                "context_index": 0,
                "task": SIMPLE,
                "method": "mpd",
                "extra_objects": extra,
                "rotation_deg": 0.0,
                "parametrization": "bspline",
                "n_samples": 100,
            }
            np.savez_compressed(
                run / "histories" / f"{key}-ctx0.npz",
                **fake_history(SIMPLE, B=6, S=4, seed=int(extra)),
                row_json=np.array(json.dumps(row)),
            )
    return run


def _png(path: Path) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG and len(data) > 3_000, path


@pytest.fixture(scope="module")
def prepared() -> pd.DataFrame:
    return prepare(synthetic_results())


@pytest.mark.parametrize("kind", rf.FIGURES, ids=lambda k: k.name)
def test_every_figure_kind_is_made(prepared, kind, tmp_path):
    from mpd.viz.report import _save

    fig = kind.make(prepared)
    assert fig is not None, kind.name
    rf.add_caption(fig, "spec synthetic (0123abcd4567) · commit 89abcdef")
    pdf = kind.name == "rotation"  # one PDF is enough to know the path works; PDFs of swarms are slow
    _save(fig, tmp_path / kind.name, formats=("png", "pdf") if pdf else ("png",), dpi=80)
    _png(tmp_path / f"{kind.name}.png")
    if pdf:
        assert (tmp_path / f"{kind.name}.pdf").read_bytes()[:4] == b"%PDF"


def test_a_caption_longer_than_a_narrow_figure_wraps_instead_of_widening_it():
    """A one-panel figure under a long caption (spec, hash, commit, run folder): the saved area keeps the figure's
    width, and the caption's words are all there, in order."""
    from matplotlib.figure import Figure

    cap = (
        "spec bspline-vs-waypoints-simple-authors (8327391fa965) · commit 8b3e5d85a8 · "
        "run bspline-vs-waypoints-simple-authors-8327391f-8b3e5d85"
    )
    fig = Figure(figsize=(3.0, 2.5), layout="constrained")
    fig.subplots().plot([0, 1], [0, 1])
    rf.add_caption(fig, cap)
    text = fig.texts[-1].get_text()
    assert text.count("\n") >= 1 and text.replace("\n", " ") == cap
    assert fig._mpd_bbox.width < 3.0 + 0.2  # unwrapped, this caption is ~5.5 in wide at 6.5 pt
    wide = Figure(figsize=(9.0, 2.5), layout="constrained")
    wide.subplots().plot([0, 1], [0, 1])
    rf.add_caption(wide, cap)
    assert wide.texts[-1].get_text() == cap  # a wide figure keeps it on one line


def test_figures_skip_cleanly_without_their_cells(prepared):
    only_main = prepared[(prepared.rotation_deg == 0) & (prepared.parametrization == "bspline")]
    only_main = only_main[only_main.task != SPHERES]
    made = {k.name: k.make(only_main) for k in rf.FIGURES}
    assert made["swarm"] is not None and made["timing"] is not None
    for name in ("rrtconnect_vs_mpd", "smoothness_kde", "parametrization_time", "rotation", "batch_size"):
        assert made[name] is None, name
    no_mpd = only_main[only_main.method != "mpd"]
    assert rf.timing_figure(no_mpd) is None


def test_main_slice_keeps_the_paper_setting(prepared):
    d, chosen = main_slice(prepared)
    assert set(d.rotation_deg) == {0.0} and set(d.parametrization) == {"bspline"}
    assert set(d[d.task == SPHERES].n_samples) == {100, 1} and chosen["n_samples"] == 100
    assert {TRAIN, EXTRA} == set(d.scene)


def test_main_slice_picks_a_cell_the_run_has_when_excludes_tie_axes():
    """Two planner settings varied in pairs (a spec's excludes drop the other combinations): each axis picked on
    its own would be (M = 1, lambda = 0.125), a cell the run does not have; picked in turn, the slice is one of
    its cells (the most frequent value of the first axis, then the second's among those rows)."""
    pairs = [(1, 1.0), (2, 0.5), (4, 0.25), (8, 0.125)]
    rows = [
        {"task": "T", "method": "mpd", "context_index": c, "planner.n_inner_steps": m, "planner.prior_weight": w,
         "fraction_valid": 0.5, "success": 1.0}
        for m, w in pairs for c in range(3)
    ]  # fmt: skip
    d, chosen = main_slice(prepare(pd.DataFrame(rows)))
    assert len(d) == 3 and chosen == {"planner.n_inner_steps": 1}  # the weight is then one value: not a choice
    assert set(zip(d["planner.n_inner_steps"], d["planner.prior_weight"])) == {(1, 1.0)}


def test_paper_numbers_beside_ours(prepared):
    t, sentences = paper_comparison(prepared)
    nums = paper_numbers()
    assert len(nums) >= 20 and all(n["sentence"] for n in nums)
    row = t[(t.task == WAREHOUSE) & (t.method == "MPD") & (t.metric == "fraction_valid")].iloc[0]
    assert row.paper == 73.5 and row.scene == EXTRA
    ours = prepared[
        (prepared.task == WAREHOUSE)
        & (prepared.method == "mpd")
        & prepared.extra_objects
        & (prepared.rotation_deg == 0)
    ]["fraction_valid"].mean()
    assert row.ours == pytest.approx(100 * ours)
    # the Spheres3D timing number: the 100-sample MPD cell, not the batch-size ones
    tt = t[(t.task == SPHERES) & (t.metric == "time_total")].iloc[0]
    assert tt.paper == 0.56 and tt.n_samples == 100
    assert "97%" in sentences[0]


def test_paper_table_markdown(prepared):
    md = paper_table(prepared)
    assert "| 73.5% |" in md and "| 96.0% |" in md and "| 2.00 cm |" in md
    assert "“For example, MPD increases the mean validity fraction of Dprior from 18.4 to 73.5%" in md


def test_paper_table_puts_the_authors_check_beside_a_fraction_valid(prepared):
    """Where the rows record the authors' check, a fraction-valid number of the paper gets our mean by that check
    beside ours (its mean over the same contexts, by hand); the other numbers a dash; without it, no column."""
    assert "authors' check" not in paper_table(prepared).split("\n\n")[1]
    d = prepared.copy()
    d["fraction_valid_authors_grid"] = (d["fraction_valid"] - 0.01 * (d["context_index"] % 3)).clip(lower=0)
    lines = next(b for b in paper_table(d).split("\n\n") if b.startswith("| task")).splitlines()  # the first table
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    col = header.index("ours, authors' check")
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[2:]]
    cell = d[(d.task == WAREHOUSE) & (d.method == "mpd") & d.extra_objects & (d.rotation_deg == 0)]
    valid = [r for r in rows if r[0] == WAREHOUSE and r[2] == "MPD" and r[3] == "fraction_valid"]
    assert len(valid) == 1 and valid[0][col].startswith(f"{100 * cell['fraction_valid_authors_grid'].mean():.2f} [")
    assert all(r[col] == "–" for r in rows if r[3] != "fraction_valid")


def test_report_builds_and_is_deterministic(tmp_path):
    run = make_run(tmp_path, n_ctx=3, small=True)
    fast = {"formats": ("png",), "dpi": 60}  # what is checked here is the Markdown; figures: the test above
    index = build_report(run, recordings=False, **fast)
    text = index.read_text()
    tables = {p: (run / "report" / p).read_text() for p in ("summary.md", "paper.md", "timing.md")}
    for kind in rf.FIGURES:
        assert f"figures/{kind.name}.png" in text, kind.name
        _png(run / "report" / "figures" / f"{kind.name}.png")
    for stem in (f"denoising-{SIMPLE}-train", f"trajectories-{SIMPLE}-train"):
        _png(run / "report" / "figures" / f"{stem}.png")
        assert f"figures/{stem}.png" in text
    assert "0123abcd4567" in text and "89abcdef" in text and "synthetic.toml" in text
    assert "Not produced" not in text
    index2 = build_report(run, recordings=False, **fast)
    assert index2.read_text() == text
    assert all((run / "report" / p).read_text() == s for p, s in tables.items())


def test_report_on_a_partial_run_skips_figures(tmp_path):
    run = tmp_path / "partial"
    run.mkdir()
    df = synthetic_results(3)
    df = df[(df.task == SIMPLE) & (df.method.isin(["gp-cost", "dprior"])) & (df.parametrization == "bspline")]
    df.to_parquet(run / "results.parquet", index=False)
    text = build_report(run, recordings=False, formats=("png",), dpi=60).read_text()
    assert "figures/swarm.png" in text and "Not produced" in text
    assert "None of the" in (run / "report" / "paper.md").read_text()


def test_paired_rows_pair_the_same_contexts(prepared):
    """MPD against each baseline: the mean of MPD - baseline over the contexts both planned, computed here with a
    merge on (seed, context), and P(MPD better) from the same pairs."""
    from mpd.viz.report_stats import paired_rows

    rows = paired_rows(prepared)
    assert {r["method"] for r in rows} == set(METHODS) - {"mpd"}
    r = next(r for r in rows if r["task"] == WAREHOUSE and r["scene"] == EXTRA and r["method"] == "dprior-cost")
    d, _ = main_slice(prepared)
    g = d[(d.task == WAREHOUSE) & d.extra_objects]
    m = g[g.method == "mpd"].merge(g[g.method == "dprior-cost"], on=["seed", "context_index"], suffixes=("", "_b"))
    diff = m["fraction_valid"] - m["fraction_valid_b"]
    fv = r["metrics"]["fraction_valid"]
    assert r["contexts"] == len(m) == 5
    assert fv.difference.value == pytest.approx(diff.mean())
    assert fv.difference.lo <= diff.mean() <= fv.difference.hi
    assert fv.p_improvement.value == pytest.approx(((diff > 0) + 0.5 * (diff == 0)).mean())
    ee = r["metrics"]["ee_pos_error"]  # lower is better: P(MPD better) counts the contexts where MPD's is lower
    e = m["ee_pos_error"] - m["ee_pos_error_b"]
    assert ee.p_improvement.value == pytest.approx(((e < 0) + 0.5 * (e == 0)).mean())


def test_report_tables_carry_intervals(tmp_path):
    run = make_run(tmp_path, n_ctx=4, histories=False, small=True)
    build_report(run, recordings=False, formats=("png",), dpi=50, reference=None)
    summary = (run / "report" / "summary.md").read_text()
    assert "Mean [95 % interval]" in summary and "## Interquartile mean" in summary and "contexts for ± 5 pp" in summary
    paired = (run / "report" / "paired.md").read_text()
    assert "| MPD vs |" in paired and "P(MPD better)" in paired
    assert "No reference run" in (run / "report" / "reproducibility.md").read_text()
    # the committed quick run as reference: no cell of this synthetic run is in it
    build_report(run, recordings=False, formats=("png",), dpi=50, reference=ROOT / "reports" / "quick")
    repro = (run / "report" / "reproducibility.md").read_text()
    assert "only in the reference" in repro and "does not reproduce it" in repro


def test_recipe_table_shows_the_goal_error_of_end_effector_goal_tasks_only():
    """On a committed run (reports/priors-cpu: Panda learning curve + the joint-goal planar arm): the EE columns
    carry the mean over the contexts (cm, deg) for the Panda rows, a dash for the joint-goal task (its samples end
    on the goal by construction), and a run of joint-goal tasks only has no EE columns."""
    from mpd.viz.report_training import recipes_table

    root = Path(__file__).parents[1] / "reports"
    d = pd.read_parquet(root / "priors-cpu" / "results.parquet").assign(scene=TRAIN)
    lines = recipes_table(d).splitlines()
    assert lines[0].endswith("| EE pos. error [cm] | EE ori. error [°] |")
    rows = {(line.split(" | ")[0][2:], line.split(" | ")[3]): line.split(" | ") for line in lines[2:]}
    planar = rows[("Planar2Link / Planar2Link", "24000")]
    assert planar[-2:] == ["–", "– |"]
    g = d[(d["task"] == SPHERES) & (d["model_steps"] == 4000)]
    panda = rows[("Spheres3D / Panda", "4000")]
    assert panda[-2].startswith(f"{100 * g['ee_pos_error'].mean():.1f} [")
    assert panda[-1].startswith(f"{g['ee_ori_error_deg'].mean():.1f} [")
    d2 = pd.read_parquet(root / "recipe-study-2d" / "results.parquet").assign(scene=TRAIN)
    assert "EE pos." not in recipes_table(d2)
    # the learning curves get a fourth panel, the goal error: drawn for the Panda, a note for the planar arm
    from mpd.viz.report_training import learning_curve_figure

    d_all = pd.read_parquet(root / "priors-cpu" / "results.parquet")
    axes = learning_curve_figure(prepare(d_all)).axes
    assert len(axes) == 4 * d_all["task"].nunique()  # four panels per task
    ee = {axes[k].get_title().split("\n")[0]: axes[k + 3] for k in range(0, len(axes), 4)}  # each row's fourth
    assert not ee["Planar2Link / Planar2Link"].axison
    panda = ee["Spheres3D / Panda"]
    assert panda.axison and panda.get_title().endswith("EE pos. error [cm]") and len(panda.lines) > 0
    assert len(learning_curve_figure(prepare(pd.read_parquet(root / "recipe-study-2d" / "results.parquet"))).axes) == 6


def test_summary_shows_a_dash_where_a_metric_does_not_apply(prepared):
    """A joint-goal task has no EE error: its EE cells are a dash, not ``0.00 [0.00, 0.00]``; an end-effector-goal
    task's are numbers."""
    from mpd.viz.report_tables import summary_table

    lines = summary_table(prepared).splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    pos, ori = header.index("EE pos. error [cm]"), header.index("EE ori. error [°]")
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]
    simple = [r for r in rows if r[0] == SIMPLE]
    panda = [r for r in rows if r[0] == WAREHOUSE]
    assert simple and all(r[pos] == r[ori] == "–" for r in simple)
    assert panda and all(r[pos][0].isdigit() and r[ori][0].isdigit() for r in panda)


def test_report_writes_pdf_only_on_demand(tmp_path):
    run = make_run(tmp_path, n_ctx=3, histories=False, small=True)
    index = build_report(run, recordings=False, dpi=40, reference=None)
    figures = run / "report" / "figures"
    assert list(figures.glob("*.png")) and not list(figures.glob("*.pdf"))
    assert "[PDF]" not in index.read_text()
    build_report(run, recordings=False, formats=("png", "pdf"), dpi=40, reference=None)
    assert {p.stem for p in figures.glob("*.pdf")} == {p.stem for p in figures.glob("*.png")}


def test_authors_grid_table_sums_the_rows_it_shows():
    """The authors'-grid section of summary.md, on a committed run: each row's two fractions valid differ by the
    flips it records (an identity of the recorded columns), and the table's cell values are the means, the paired
    mean difference and the sums of those rows, computed here by hand; a run without the columns says so."""
    from mpd.viz.report_stats import authors_grid_table

    raw = pd.read_parquet(ROOT / "reports" / "eval-simple-authors" / "results.parquet")
    n = raw["n_samples"].astype(float)
    flips = (raw["n_flips_valid_to_invalid"] - raw["n_flips_invalid_to_valid"]) / n
    np.testing.assert_allclose(raw["fraction_valid"] - raw["fraction_valid_authors_grid"], flips, atol=1e-9)

    d = prepare(raw)
    lines = authors_grid_table(d).splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = {
        (r[0], r[1], r[2], r[3]): dict(zip(header, r))
        for r in ([c.strip() for c in line.strip("|").split("|")] for line in lines[2:])
    }
    assert len(rows) == d.groupby(["task", "scene", "method", "parametrization"]).ngroups
    for (method, extra), g in d.groupby(["method", "extra_objects"]):
        g = g[g.parametrization == "bspline"]
        row = rows[(SIMPLE, EXTRA if extra else TRAIN, method_label(method), "bspline")]
        diff = 100 * (g["fraction_valid_authors_grid"] - g["fraction_valid"])
        assert row["contexts"] == str(len(g)) and row["trajectories"] == str(int(g["n_samples"].sum()))
        assert row["fraction valid, mpd [%]"] == f"{100 * g['fraction_valid'].mean():.1f}"
        assert row["authors' grid [%]"] == f"{100 * g['fraction_valid_authors_grid'].mean():.1f}"
        assert row["authors' − mpd [pp]"].strip("*").startswith(f"{diff.mean():+.1f} [")
        assert row["valid → invalid"] == str(int(g["n_flips_valid_to_invalid"].sum()))
        assert row["invalid → valid"] == str(int(g["n_flips_invalid_to_valid"].sum()))

    older = d.drop(columns=["fraction_valid_authors_grid"])
    assert "predate" in authors_grid_table(older)
    part = d.copy()
    part.loc[part.index[:5], "fraction_valid_authors_grid"] = np.nan
    assert authors_grid_table(part).endswith("5 rows predate the check and are left out.")
