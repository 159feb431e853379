"""The tables of reports/mbm-mpd/README.md: planners with a learned prior (``mpd bench mbm prior``) beside RRTConnect
(``mpd bench mbm run``) on the same held-out MotionBenchMaker problems.

Per family (and over all families): success over the problems with its 95 % Wilson interval (a problem whose goal
mpd's checker refuses counts as a failure), a prior's fraction of valid trajectories (mean over problems, 95 %
bootstrap interval), the time of a plan (median over the problems with a plan, 95 % bootstrap interval of the median)
and the joint-space path length of the solution (RRTConnect's simplified path; a prior's shortest valid trajectory),
median [IQR]. Then the paired differences of fraction valid between the priors' planners (the paper's adaptation
claim: MPD >= Dprior+Cost >= Dprior), over the same problems.

    python benchmarks/tools/mbm_prior_report.py --rrtconnect reports/mbm-rrtconnect/grasp-ignored \\
        reports/mbm-mpd/mpd reports/mbm-mpd/dprior-cost reports/mbm-mpd/dprior --write reports/mbm-mpd/README.md

``--write`` replaces what lies between ``<!-- tables -->`` and ``<!-- /tables -->`` in the given file (``--marker
NAME``: between ``<!-- NAME -->`` and ``<!-- /NAME -->``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from mbm_report import _ms, _pct, median_interval  # noqa: E402

from mpd import stats  # noqa: E402
from mpd.data.mbm import FAMILIES  # noqa: E402
from mpd.experiments import mbm as mbm_run  # noqa: E402

LABELS = {"mpd": "MPD", "dprior-cost": "Dprior+Cost", "dprior": "Dprior", "cvae": "CVAE", "cvae-cost": "CVAE+Cost"}


def _load(run: Path) -> dict:
    meta = json.loads((run / "settings.json").read_text())
    recs = mbm_run.read_results(run)
    if meta["baseline"] == "prior":
        s = mbm_run.PriorSettings(**meta["settings"])
        label = LABELS.get(s.method, s.method)
    else:
        s = mbm_run.BaselineSettings(**meta["settings"])
        label = f"RRTConnect ({s.time_limit:g} s)"
    return {"run": run, "meta": meta, "settings": s, "label": label, "records": recs}


def _length(rows: list[dict]) -> str:
    x = np.asarray([r["path_length"] for r in rows if r["success"] and r["path_length"] is not None], dtype=float)
    if len(x) == 0:
        return "–"
    return f"{np.median(x):.2f} [{np.percentile(x, 25):.2f}, {np.percentile(x, 75):.2f}]"


def _row(label: str, run: dict, rows: list[dict]) -> list[str]:
    solved = sum(bool(r["success"]) for r in rows)
    prior = run["meta"]["baseline"] == "prior"
    if prior:
        fv = [r["fraction_valid"] if r["fraction_valid"] is not None else 0.0 for r in rows]
        e = stats.bootstrap(fv)
        frac = f"{100 * e.value:.1f} [{100 * e.lo:.1f}, {100 * e.hi:.1f}]"
        times = [r["time_s"] for r in rows if r["time_first_s"] is not None]
    else:
        frac = "–"
        times = [r["time_first_s"] for r in rows if r["success"]]
    t, lo, hi = median_interval(times)
    return [label, run["label"], _pct(solved, len(rows)), frac, f"{_ms(t)} [{_ms(lo)}, {_ms(hi)}]", _length(rows)]


def _select(run: dict, family: str | None, keep: set) -> list[dict]:
    rows = [r for r in run["records"] if (r["family"], r["index"]) in keep]
    return [r for r in rows if family is None or r["family"] == family]


def tables(rrt: Path, priors: list[Path]) -> str:
    runs = [_load(p) for p in priors]
    first, last = runs[0]["settings"].first, runs[0]["settings"].last
    grasp = runs[0]["settings"].grasp_target
    keep = {(r["family"], r["index"]) for r in runs[0]["records"]}
    for run in runs[1:]:
        if {(r["family"], r["index"]) for r in run["records"]} != keep:
            raise SystemExit(f"{run['run']} has other problems than {runs[0]['run']}")
    base = _load(rrt)
    if base["settings"].grasp_target != grasp:
        raise SystemExit(f"{rrt} plans with grasp_target {base['settings'].grasp_target}, the priors with {grasp}")
    missing = keep - {(r["family"], r["index"]) for r in base["records"]}
    if missing:
        raise SystemExit(f"{rrt} lacks {len(missing)} of the priors' problems")
    everything = [base, *runs]
    fams = [f for f in FAMILIES if any(r["family"] == f for r in runs[0]["records"])]
    out = [
        f"**Held-out problems {first}-{last} of each family** (grasp_target = {grasp}; n = problems per family)",
        "",
        "| family | planner | success [95 % Wilson] | fraction valid, % [95 % CI] | plan time, ms: median [95 % CI] "
        "| path length, rad: median [IQR] |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for fam in [*fams, None]:
        name = fam or f"**all {len(keep)}**"
        for run in everything:
            cells = _row(name, run, _select(run, fam, keep))
            if fam is None:
                cells = [f"**{c}**" if i > 1 and c != "–" else c for i, c in enumerate(cells)]
            out.append("| " + " | ".join(cells) + " |")
    # paired differences of fraction valid between the priors' planners
    by = {run["settings"].method: run for run in runs}
    pairs = [
        (a, b) for a, b in (("mpd", "dprior-cost"), ("dprior-cost", "dprior"), ("mpd", "dprior")) if a in by and b in by
    ]
    if pairs:
        out += [
            "",
            "**Paired differences of fraction valid** (pp, mean over the same problems [95 % bootstrap CI])",
            "",
            "| family | " + " | ".join(f"{LABELS[a]} − {LABELS[b]}" for a, b in pairs) + " |",
            "| --- | " + " | ".join("---:" for _ in pairs) + " |",
        ]
        for fam in [*fams, None]:
            cells = [fam or f"**all {len(keep)}**"]
            for a, b in pairs:
                va, vb = (
                    {(r["family"], r["index"]): r["fraction_valid"] or 0.0 for r in _select(by[m], fam, keep)}
                    for m in (a, b)
                )
                ks = sorted(va)
                d = stats.paired([va[k] for k in ks], [vb[k] for k in ks]).difference
                cells.append(f"{100 * d.value:+.1f} [{100 * d.lo:+.1f}, {100 * d.hi:+.1f}]")
            out.append("| " + " | ".join(cells) + " |")
    out += ["", "Machines (from each folder's `provenance.json`):", ""]
    for run in everything:
        inv = mbm_run.read_provenance(run["run"])
        cpus = sorted({i["cpu"] for i in inv})
        commits = sorted({str(i["git_commit"])[:10] + (" (dirty tree)" if i.get("git_dirty") else "") for i in inv})
        threads = sorted({i["torch_threads"] for i in inv})
        n = sum(i["problems"] for i in inv)
        when = f"{min(i['started'] for i in inv)} to {max(i['finished'] or i['started'] for i in inv)}" if inv else "?"
        model = run["meta"].get("model_identity")
        out.append(
            f"- {run['label']} (`{run['run']}`): {n} problems planned, {when}, CPU {', '.join(cpus)}, torch threads "
            f"{', '.join(map(str, threads))}, commit {', '.join(commits)}" + (f", model `{model}`" if model else "")
        )
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("priors", nargs="+", type=Path, help="run folders of mpd bench mbm prior")
    ap.add_argument("--rrtconnect", type=Path, required=True, help="the run folder of mpd bench mbm run")
    ap.add_argument("--write", type=Path, default=None, help="replace the tables between the markers of this file")
    ap.add_argument("--marker", default="tables", help="the markers <!-- NAME --> and <!-- /NAME --> (default: tables)")
    a = ap.parse_args()
    text = tables(a.rrtconnect, a.priors)
    if a.write is None:
        print(text)
        return
    doc = a.write.read_text()
    begin, end = f"<!-- {a.marker} -->", f"<!-- /{a.marker} -->"
    i, j = doc.index(begin), doc.index(end)
    a.write.write_text(doc[: i + len(begin)] + "\n" + text + doc[j:])
    print(f"wrote {a.write}")


if __name__ == "__main__":
    main()
