"""reports/README.md is what `mpd report index` makes from the committed report folders."""

from __future__ import annotations

from pathlib import Path

from mpd.viz.reports_index import reports_index, superseded_by

ROOT = Path(__file__).resolve().parents[1]
REPORTS = ROOT / "reports"


def test_committed_index_is_what_the_folders_give():
    assert (REPORTS / "README.md").read_text() == reports_index(REPORTS), (
        "reports/README.md disagrees with the report folders: regenerate it with `mpd report index`"
    )


def test_every_report_folder_is_listed_once():
    text = (REPORTS / "README.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| [")]
    folders = sorted(p.name for p in REPORTS.iterdir() if p.is_dir())
    assert sorted(r.split("]")[0][3:] for r in rows) == folders


def test_a_cpu_report_is_superseded_by_its_gpu_priors_twin_else_its_authors_twin():
    names = {"eval-panda-cpu", "eval-panda-gpu-priors", "eval-2d-cpu"}
    assert superseded_by("eval-panda-cpu", names) == "eval-panda-gpu-priors"
    assert superseded_by("eval-2d-cpu", names) is None
    assert superseded_by("eval-panda-gpu-priors", names) is None
    assert superseded_by("eval-2d-cpu", names | {"eval-2d-authors"}) == "eval-2d-authors"
    assert superseded_by("eval-2d-cpu", names | {"eval-2d-authors", "eval-2d-gpu-priors"}) == "eval-2d-gpu-priors"
    assert superseded_by("eval-2d-authors", names | {"eval-2d-authors"}) is None


def test_index_of_a_changed_folder_differs(tmp_path):
    """A report whose results change changes the index (the headline is read from the table)."""
    import shutil

    import pandas as pd

    for name in ("quick", "compile-2d"):
        shutil.copytree(REPORTS / name, tmp_path / name, ignore=shutil.ignore_patterns("report"))
    before = reports_index(tmp_path)
    df = pd.read_parquet(tmp_path / "quick" / "results.parquet")
    df.loc[df["method"] == "mpd", "fraction_valid"] *= 0.5
    df.to_parquet(tmp_path / "quick" / "results.parquet", index=False)
    assert reports_index(tmp_path) != before


def test_the_priors_column_names_a_model_of_its_own_profile():
    from mpd.viz.reports_index import _priors

    spec = {"tasks": {"A": {"profile": "cpu", "cvae_profile": "gpu"}, "B": {}}}
    assert _priors(spec) == "`cpu` (CVAE `gpu`)"
    spec["tasks"]["A"]["models"] = {"diffusion-bspline": {"profile": "paper", "train_steps": 140000}}
    spec["tasks"]["B"]["models"] = {"cvae": {"train_steps": 500}}
    assert _priors(spec) == "`cpu` (CVAE `gpu`); cvae `cpu` 500 steps, diffusion-bspline `paper` 140,000 steps"
