"""Where the time of dataset generation goes: one chunk of N contexts of a dataset definition, computed in this
process under cProfile (one thread), split into context sampling (IK for end-effector goals), planning (OMPL with our
validity callbacks) and the rest (B-spline fits, ground-truth check), with the top functions by own time.

    python benchmarks/tools/profile_data.py EnvWarehouse-RobotPanda-small --contexts 20 --out profile.txt

The chunk is computed from the definition's first N contexts, as `mpd data generate` would (same seeds), but is
not stored. Set-up (checker, planner, IK solver construction) is timed separately.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import io
import pstats
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("definition")
    ap.add_argument("--contexts", type=int, default=20)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from mpd.data.definition import ResolvedDefinition, load_definition
    from mpd.data.generate import _tools, compute_chunk

    rd = load_definition(args.definition)
    defn = dataclasses.replace(rd.definition, n_contexts=args.contexts, chunk_size=args.contexts)
    rd = ResolvedDefinition(defn, rd.task, rd.path, rd.identity + "-profile")
    t = time.perf_counter()
    _tools(rd)
    setup = time.perf_counter() - t
    prof = cProfile.Profile()
    t, c = time.perf_counter(), time.process_time()
    prof.enable()
    arrays, meta = compute_chunk(rd, 0)
    prof.disable()
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    ok = int(arrays["success"].sum())
    ctx, plan = sum(meta["context_time"]), sum(meta["plan_time"])
    lines = [
        f"{rd.name}: {args.contexts} contexts, {ok} paths; set-up {setup:.2f} s (not profiled)",
        f"wall {wall:.2f} s, CPU {cpu:.2f} s (this process) -> {ok / wall:.2f} paths/s on one core",
        f"  context sampling {ctx:.2f} s ({100 * ctx / wall:.0f} %), "
        f"planning {plan:.2f} s ({100 * plan / wall:.0f} %), "
        f"rest (fits, ground truth) {wall - ctx - plan:.2f} s ({100 * (wall - ctx - plan) / wall:.0f} %)",
        "(times under cProfile: its overhead inflates Python-heavy parts)",
        "",
    ]
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(args.top)
    text = "\n".join(lines) + buf.getvalue()
    if args.out:
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
