"""Peak memory of loading and training on a paper-size dataset, measured on SYNTHETIC data in the real chunk format.

EnvSpheres3D-paper is 1 M contexts (2 M paths with the reversed copies; the dense paths alone ~7 GB as float32).
Generating it takes days of OMPL here, so this writes a dataset of that size in the real chunk format (the same
writer, archives, sidecars and lock as `mpd data generate`) with random but well-formed content: uniform start
and goal configurations within the joint limits, control points on the straight segment between them with a
random bend, the dense path = the B-spline of those control points (so paths and fits agree), a random goal pose.
It is **marked synthetic** everywhere it could be mistaken for real data: the definition's name ends in
``-SYNTHETIC-<n>``, its seed is not a real dataset's, every chunk sidecar says ``"synthetic": true``, loading it
warns on stderr, and an experiment run refuses it.

Then, each in a fresh process, it measures the peak RSS (``ru_maxrss`` of that child) of
  * ``load``:  ``load_dataset`` (every chunk verified by sha256; paths memory-mapped, read where indexed);
  * ``train``: ``mpd train`` for a few steps of the `cpu` profile (dataset loaded, training arrays built, steps run);
at two sizes (default 50k and 1M contexts) and writes a JSON summary.

    python benchmarks/memory_paper_size.py --sizes 50000 1000000 --out benchmarks/results/2026-12-02-memory.json

The data goes under ``$MPD_CACHE`` (default ``.cache``; ~4.4 GB for 1 M contexts) and is removed with ``--clean``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

TASK = "EnvSpheres3D-RobotPanda"
SYNTHETIC_SEED = 987_654_321  # no real definition uses it


def write_synthetic(n: int, root: Path, chunk_size: int = 1000) -> Path:
    """Write (or finish) a synthetic dataset of ``n`` contexts; returns its definition file."""
    from mpd.data.definition import load_definition
    from mpd.data.generate import _definition_record, _write_lock
    from mpd.data.storage import verify_chunk, write_atomic, write_chunk
    from mpd.trajectory import make_parametrization

    name = f"{TASK}-SYNTHETIC-{n}"
    path = root / f"{name}.toml"
    path.write_text(
        textwrap.dedent(f"""
        # SYNTHETIC: random, well-formed paths in the real chunk format, for memory measurements only
        name = "{name}"
        task = "{TASK}"
        description = "SYNTHETIC data (random paths), for measurements only; never real planning results"
        n_contexts = {n}
        seed = {SYNTHETIC_SEED}
        chunk_size = {chunk_size}
        [checker]
        kind = "spheres"
        """)
    )
    rd = load_definition(path)
    task, d = rd.task, rd.definition
    rd.data_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(rd.data_dir / "definition.json", (json.dumps(_definition_record(rd), indent=1) + "\n").encode())
    param = make_parametrization(task, "bspline")
    basis = np.asarray(param.basis, dtype=np.float64)  # (n_points, n_control_points)
    lo, hi = task.robot.q_min.numpy(), task.robot.q_max.numpy()
    K, T, dof = basis.shape[1], basis.shape[0], task.dof
    for i in range(d.n_chunks):
        if verify_chunk(rd.data_dir, i)[0]:
            continue
        start, stop = d.chunk_range(i)
        m = stop - start
        rng = np.random.default_rng([SYNTHETIC_SEED, i])
        qs, qg = rng.uniform(lo, hi, (m, dof)), rng.uniform(lo, hi, (m, dof))
        s = np.linspace(0.0, 1.0, K)[None, :, None]
        bend = rng.normal(0.0, 0.1, (m, 1, dof)) * np.sin(np.pi * s)
        cps = np.clip(qs[:, None] + s * (qg - qs)[:, None] + bend, lo, hi)
        paths = np.einsum("tk,mkd->mtd", basis, cps)
        rot, _ = np.linalg.qr(rng.normal(size=(m, 3, 3)))
        arrays = {
            "context_id": np.arange(start, stop, dtype=np.int64),
            "q_start": qs,
            "q_goal": qg,
            "source": np.zeros(m, dtype=np.int8),
            "status": np.zeros(m, dtype=np.int8),
            "success": np.ones(m, dtype=bool),
            "n_vertices": np.full(m, 2, dtype=np.int16),
            "path": paths.astype(np.float32),
            "control_points": cps.astype(np.float32),
            "fit_in_range": np.ones(m, dtype=bool),
            "fit_free": np.ones(m, dtype=bool),
            "ee_pos": rng.uniform(-0.8, 0.8, (m, 3)),
            "ee_rot": rot,
        }
        meta = {
            "contexts": [start, stop],
            "successes": m,
            "context_time": [0.0] * m,
            "plan_time": [0.0] * m,
            "wall_s": 0.0,
            "cpu_s": 0.0,
            "synthetic": True,
        }
        write_chunk(rd.data_dir, i, arrays, meta)
        assert K == cps.shape[1] and T == paths.shape[1]
    _write_lock(rd, None, None, create=False)
    return path


PROBE = {
    "load": textwrap.dedent("""
        import sys, time
        from mpd.data.dataset import load_dataset
        t = time.perf_counter()
        ds = load_dataset(sys.argv[1], generate_missing=False, progress=False)
        print(f"paths {len(ds)} ({ds.paths.shape}), control points {ds.control_points.nbytes / 2**30:.2f} GiB, "
              f"{time.perf_counter() - t:.1f} s", file=sys.stderr)
    """),
}


def _peak_rss(cmd: list[str], env: dict) -> tuple[float, float, int]:
    """(peak RSS in GiB, wall s, exit code) of one child process."""
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return usage.ru_maxrss / 2**20, time.perf_counter() - t, proc.returncode  # ru_maxrss: KiB on Linux


def _forget_models(definition: Path) -> None:
    """Remove cached models trained on this synthetic dataset, so that the `train` probe trains (not finds) one."""
    import shutil

    from mpd.data.definition import load_definition
    from mpd.models.train import list_models

    lock = json.loads((load_definition(definition).data_dir / "lock.json").read_text())
    for m in list_models(TASK):
        if m.get("dataset_hash") == lock["content_hash"]:
            shutil.rmtree(Path(m["path"]).parent)


def measure(definition: Path, steps: int) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    _forget_models(definition)
    out = {}
    rss, wall, rc = _peak_rss([sys.executable, "-c", PROBE["load"], str(definition)], env)
    out["load"] = {"peak_rss_gib": round(rss, 3), "wall_s": round(wall, 1), "exit_code": rc}
    cmd = [
        sys.executable, "-m", "mpd.cli", "train", "--task", TASK, "--dataset", str(definition), "--steps", str(steps),
        "--threads", "1", "--no-shipped",
    ]  # fmt: skip
    rss, wall, rc = _peak_rss(cmd, env)
    out["train"] = {"peak_rss_gib": round(rss, 3), "wall_s": round(wall, 1), "exit_code": rc, "steps": steps}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[50_000, 1_000_000])
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--clean", action="store_true", help="remove the synthetic data afterwards")
    args = ap.parse_args()
    from mpd.data.definition import load_definition
    from mpd.provenance import cpu_model, provenance

    root = Path(tempfile.mkdtemp(prefix="mpd-synthetic-"))
    results = {"synthetic": True, "task": TASK, "cpu": cpu_model(), "provenance": provenance(), "sizes": {}}
    for n in args.sizes:
        t = time.perf_counter()
        definition = write_synthetic(n, root)
        rd = load_definition(definition)
        disk = sum(p.stat().st_size for p in rd.data_dir.glob("chunk-*.npz"))
        res = {"contexts": n, "paths": 2 * n, "disk_gib": round(disk / 2**30, 3)}
        res["write_s"] = round(time.perf_counter() - t, 1)
        res.update(measure(definition, args.steps))
        results["sizes"][str(n)] = res
        print(json.dumps(res), file=sys.stderr)
        if args.clean:
            import shutil

            shutil.rmtree(rd.data_dir)
    text = json.dumps(results, indent=1) + "\n"
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    main()
