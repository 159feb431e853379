"""The tables of reports/mbm-rrtconnect/README.md from the run folders of ``mpd bench mbm run``.

Per family and grasp-target setting: the goals valid under mpd's checker (with why not: in the scene, beyond mpd's
joint limits), RRTConnect's success over all 100 problems with its 95 % Wilson interval (a problem whose start or
goal is invalid counts as a failure: it is not planned), the time to the first solution (median over the solved
problems and a 95 % percentile bootstrap interval of the median, seeded), the joint-space path length (median
[IQR]) and the paths mpd's checker passes along their length. Then the run's machines and the published figures.

    python benchmarks/tools/mbm_report.py reports/mbm-rrtconnect/grasp-obstacle reports/mbm-rrtconnect/grasp-ignored
    python benchmarks/tools/mbm_report.py RUN... --write reports/mbm-rrtconnect/README.md   # between its markers

``--write`` replaces what lies between ``<!-- tables -->`` and ``<!-- /tables -->`` in the given file; without it
the tables go to stdout.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from scipy import stats

from mpd.data import mbm
from mpd.experiments import mbm as mbm_run
from mpd.stats import wilson

SEED = 0
N_RESAMPLES = 2000
BEGIN, END = "<!-- tables -->", "<!-- /tables -->"


def median_interval(x, seed: int = SEED) -> tuple[float, float, float]:
    """(median, lo, hi): the median of ``x`` and its 95 % percentile bootstrap interval (NaN bounds below 2)."""
    x = np.asarray([v for v in x if v is not None and math.isfinite(v)], dtype=float)
    if len(x) == 0:
        return (math.nan, math.nan, math.nan)
    m = float(np.median(x))
    if len(x) < 2 or np.all(x == x[0]):
        return (m, m, m) if len(x) >= 2 else (m, math.nan, math.nan)
    res = stats.bootstrap(
        (x,),
        np.median,
        n_resamples=N_RESAMPLES,
        vectorized=True,
        confidence_level=0.95,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    return (m, float(res.confidence_interval.low), float(res.confidence_interval.high))


def _ms(x: float) -> str:
    return "–" if math.isnan(x) else f"{1000 * x:.0f}" if x >= 0.1 else f"{1000 * x:.1f}"


def _pct(k: int, n: int) -> str:
    lo, hi = wilson(k, n)
    return f"{k}/{n} = {100 * k / n:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}]"


def family_row(name: str, recs: list[dict], validity: dict | None) -> list[str]:
    n = len(recs)
    solved = [r for r in recs if r["success"]]
    planned = [r for r in recs if r["status"] not in ("invalid_start", "invalid_goal")]
    if validity is not None:
        in_scene = int((~validity["goal_env_free"]).sum())
        beyond = int((~validity["goal_within_limits"]).sum())
        goals = f"{int(validity['goal_valid'].sum())} ({in_scene} in the scene, {beyond} beyond limits)"
    else:
        goals = str(len(planned))
    t, lo, hi = median_interval([r["time_first_s"] for r in solved])
    lengths = np.asarray([r["path_length"] for r in solved], dtype=float)
    length = (
        f"{np.median(lengths):.2f} [{np.percentile(lengths, 25):.2f}, {np.percentile(lengths, 75):.2f}]"
        if len(lengths)
        else "–"
    )
    timeouts = sum(r["status"] in ("timeout", "budget") for r in recs)
    valid = sum(bool(r["valid_mpd"]) for r in solved)
    return [
        name,
        goals,
        _pct(len(solved), n),
        f"{len(solved)}/{len(planned)}" if planned else "–",
        str(timeouts),
        f"{_ms(t)} [{_ms(lo)}, {_ms(hi)}]",
        length,
        f"{valid}/{len(solved)}",
    ]


def table(run: Path, imported) -> str:
    meta = json.loads((run / "settings.json").read_text())
    settings = mbm_run.BaselineSettings(**meta["settings"])
    recs = mbm_run.read_results(run)
    header = [
        "family",
        "goals valid (of 100)",
        "success [95 % Wilson]",
        "of planned",
        "timeouts",
        "first solution, ms: median [95 % CI]",
        "path length, rad: median [IQR]",
        "mpd's checker passes",
    ]
    rows = []
    all_valid = None
    for fam in mbm.FAMILIES:
        fam_recs = sorted((r for r in recs if r["family"] == fam), key=lambda r: r["index"])
        if not fam_recs:
            continue
        v = None
        if imported is not None:
            v = mbm.endpoint_validity(imported, fam, settings.cylinder_slabs, settings.grasp_target)
            all_valid = v if all_valid is None else {k: np.concatenate([all_valid[k], v[k]]) for k in v}
        rows.append(family_row(fam, fam_recs, v))
    rows.append(family_row(f"all {len(recs)}", recs, all_valid))
    rows[-1] = [f"**{c}**" for c in rows[-1]]
    lines = [
        f"**grasp_target = {settings.grasp_target}** (`{run.as_posix()}`; time limit {settings.time_limit:g} s, "
        f"seed {settings.seed}, cylinders as {settings.cylinder_slabs} boxes)",
        "",
        "| " + " | ".join(header) + " |",
        "| " + " | ".join(["---"] + ["---:"] * (len(header) - 1)) + " |",
    ]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


# Published figures (planner, hardware, problems, success, time, source), quoted as their sources give them
PUBLISHED = (
    (
        "cuRoboV2",
        "NVIDIA RTX 6000 Ada (GPU)",
        "MBM + MπNets, pose goals",
        "99.73 %",
        "38 ms mean",
        "[1], as quoted for the paper (its text not checked here)",
    ),
    (
        "cuRobo v0.7.6",
        "NVIDIA RTX 6000 Ada (GPU)",
        "2600: MBM + MπNets, pose goals",
        "99.85 %",
        "39 ms mean, 31 ms median",
        "[2]",
    ),
    ("cuRobo v0.7.6", "NVIDIA RTX 6000 Ada (GPU)", "MBM, 800, pose goals", "100 %", "42 ms mean, 31 ms median", "[2]"),
    (
        "VAMP RRTConnect",
        "one core of a consumer desktop PC",
        "MBM Panda, 7 x 100, joint goals",
        "–",
        "35 µs median",
        "[3], [4]",
    ),
)


def comparison(runs: list[Path]) -> str:
    """The published figures and this report's overall ones, one row each."""
    header = ["planner", "hardware", "problems", "success", "time to a solution", "source"]
    rows = [list(r) for r in PUBLISHED]
    for run in runs:
        meta = json.loads((run / "settings.json").read_text())
        recs = mbm_run.read_results(run)
        t = np.asarray([r["time_first_s"] for r in recs if r["success"]], dtype=float)
        cpus = ", ".join(sorted({m["cpu"] for m in mbm_run.read_provenance(run)}))
        k, n = sum(bool(r["success"]) for r in recs), len(recs)
        rows.append(
            [
                f"mpd's RRTConnect (OMPL), grasp_target = {meta['settings']['grasp_target']}",
                f"{cpus}, 1 thread, shared machine",
                f"MBM Panda, {n}, joint goals",
                f"{100 * k / n:.1f} %",
                f"{1000 * t.mean():.0f} ms mean, {1000 * np.median(t):.0f} ms median (first solution)",
                "this report",
            ]
        )
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(["---"] * len(header)) + " |"]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def machines(runs: list[Path]) -> str:
    out = []
    for run in runs:
        for m in mbm_run.read_provenance(run):
            out.append(
                f"- `{run.name}`: {m['problems']} problems, {m['started']} to {m['finished']}, CPU {m['cpu']} "
                f"({m['cpu_count']} cores, torch threads {m['torch_threads']}, OMP_NUM_THREADS "
                f"{m['OMP_NUM_THREADS']}), OMPL {m['ompl']}, torch {m['libraries'].get('torch')}, mpd {m['mpd']} at "
                f"commit `{m['git_commit'][:10]}`{' (dirty tree)' if m['git_dirty'] else ''}"
            )
    return "\n".join(out)


def tables(runs: list[Path], validity: bool = True) -> str:
    imported = mbm.import_problems() if validity else None
    parts = [table(run, imported) for run in runs]
    parts.append("Beside the published figures (sources below):\n\n" + comparison(runs))
    parts.append("Machines (from each folder's `provenance.json`):\n\n" + machines(runs))
    return "\n\n".join(parts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders of `mpd bench mbm run`")
    ap.add_argument("--write", type=Path, default=None, help="replace the tables between the markers of this file")
    ap.add_argument("--no-validity", action="store_true", help="goals valid from the runs' statuses only")
    args = ap.parse_args()
    text = tables(args.runs, validity=not args.no_validity)
    if args.write is None:
        print(text)
        return
    page = args.write.read_text()
    if BEGIN not in page or END not in page:
        raise SystemExit(f"{args.write}: no {BEGIN} ... {END} markers")
    head, rest = page.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    args.write.write_text(f"{head}{BEGIN}\n{text}\n{END}{tail}")


if __name__ == "__main__":
    main()
