"""Run a spec end to end on a local multi-node Ray cluster (``ray.cluster_utils.Cluster``: several raylets on this
machine, each with its own cache unless ``--shared-cache``), the way a user checks a cluster before the real run.

    python benchmarks/tools/local_cluster.py paper-main --scale 0.00001 --nodes 2 --report

Prints the wall time, the run folder and which node did what (the manifest's ``ray_nodes``).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("spec")
    ap.add_argument("--scale", type=float, default=None)
    ap.add_argument("--nodes", type=int, default=2)
    ap.add_argument("--cpus-per-node", type=int, default=1)
    ap.add_argument("--shared-cache", action="store_true", help="every node uses the driver's $MPD_CACHE")
    ap.add_argument("--report", action="store_true")
    args = ap.parse_args()

    import ray
    from ray.cluster_utils import Cluster

    from mpd.experiments.runner import Runner
    from mpd.experiments.spec import load_spec, scale_spec

    spec = load_spec(args.spec)
    if args.scale:
        spec = scale_spec(spec, args.scale)
    node_caches = Path(tempfile.mkdtemp(prefix="mpd-nodes-"))
    t0 = time.perf_counter()
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": args.cpus_per_node})
    try:
        for k in range(1, args.nodes):
            env = {} if args.shared_cache else {"MPD_CACHE": str(node_caches / f"node{k}")}
            cluster.add_node(num_cpus=args.cpus_per_node, env_vars=env)
        cluster.wait_for_nodes()
        runner = Runner(spec, executor="ray", address=cluster.address)
        run_dir = runner.run()
    finally:
        ray.shutdown()
        cluster.shutdown()
    wall = time.perf_counter() - t0
    man = json.loads((run_dir / "manifest.json").read_text())
    summary = {
        "spec": spec.name,
        "nodes": args.nodes,
        "cpus_per_node": args.cpus_per_node,
        "shared_cache": args.shared_cache,
        "wall_s": round(wall, 1),
        "run_dir": str(run_dir),
        "n_rows": man.get("n_rows"),
        "status": man.get("status"),
        "ray_nodes": man.get("ray_nodes"),
        "node_caches": None if args.shared_cache else str(node_caches),
        "pid": os.getpid(),
    }
    if args.report:
        from mpd.viz.report import build_report

        t = time.perf_counter()
        summary["report"] = str(build_report(run_dir))
        summary["report_s"] = round(time.perf_counter() - t, 1)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
