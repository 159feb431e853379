"""The end-effector numbers of the paper in a report's paper.md: every aggregate the results hold, the paper's
definition (mean over contexts of each context's mean over its valid samples, SE(3)-log errors) marked, and that
one is what the main table of the paper's numbers uses."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from mpd.viz.report_data import prepare
from mpd.viz.report_tables import EE_AGGREGATES, ee_aggregates_table, paper_comparison, paper_table

RESULTS = Path(__file__).resolve().parents[1] / "reports" / "eval-panda-gpu-priors" / "results.parquet"


def test_ee_aggregates_mark_the_paper_definition_used_by_the_main_table():
    d = prepare(pd.read_parquet(RESULTS))
    table = ee_aggregates_table(d)
    rows = [line.split(" | ") for line in table.splitlines()[2:]]
    main, _ = paper_comparison(d)
    ee = main[main["metric"].isin(list(EE_AGGREGATES))]
    # CVAE, Dprior, Dprior+Cost, MPD x position, orientation (training scene); Dprior, MPD orientation (extra)
    assert len(ee) == 10
    assert len(rows) == sum(len(EE_AGGREGATES[m]) for m in ee["metric"])
    starred = [r for r in rows if r[5].startswith("★")]
    assert len(starred) == len(ee)
    # the starred aggregate is the column the main table compares: the same mean, to the printed digits
    for r in starred:
        assert r[5] == "★ " + EE_AGGREGATES[r[3]][0][0]
    mpd_pos = [r for r in starred if r[2] == "MPD" and r[3] == "ee_pos_error"][0]
    ours = float(main[(main["method"] == "MPD") & (main["metric"] == "ee_pos_error")]["ours"].iloc[0])
    assert mpd_pos[6].startswith(f"{ours:.3f}")
    assert "## End-effector errors: every aggregate" in paper_table(d)


def test_no_ee_section_without_ee_numbers():
    d = prepare(pd.read_parquet(RESULTS))
    assert ee_aggregates_table(d[d["task"] == "EnvSpheres3D-RobotPanda"]) == ""
