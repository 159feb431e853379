"""Train priors on a GPU inside a deadline, and bring them back in their shipped form.

An offline GPU machine holds the working tree only (64 MiB) and runs for minutes, not hours. So the training
arrays are exported here, the step budget is fitted there to the time left, and what comes back is the shipped file
(EMA weights, bfloat16) with its lock, the training record (``meta.json``) and a summary:

    # here: the arrays of a task's dataset (the dataset of the task's `cpu` profile runs by default)
    python benchmarks/gpu_train.py export EnvSpheres3D-RobotPanda --dataset EnvSpheres3D-RobotPanda-cpu --out .gpu/s.npz
    # there (in the same call as the rest of the device work; several trainings can share the GPU: each is bound by
    # its own kernel launches, not by the GPU):
    python benchmarks/gpu_train.py train .gpu/s.npz --profile gpu --deadline $(( $(date +%s) + 480 )) --out $OUT

The task's training profile (``[training.gpu]``) gives every setting but the number of steps, which is chosen on the
machine: a 200- and a 600-step probe measure the training loop's steps/s (from their difference) and the setup's
seconds, and the run takes the largest multiple of 1000 steps that ends, at 90 % of that rate, before the deadline.
The summary names it; a profile with those steps gives the same model identity here (the identity is made of the
dataset's content hash, the network and training settings and the seed), so the shipped file is found by every spec
that names the profile.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PROBE_STEPS = 200
SAFETY = 0.9
MARGIN_S = 20.0  # the last validation, the shipped file, the copies


def export(args) -> int:
    import numpy as np

    from mpd.data.dataset import load_dataset
    from mpd.models.data import training_arrays
    from mpd.tasks import load_task

    task = load_task(args.task)
    arrays = training_arrays(task, load_dataset(args.dataset), args.parametrization)
    x = arrays.x
    meta = {
        "x_sha256": hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest(),
        "task_name": arrays.task_name,
        "task_hash": arrays.task_hash,
        "dataset_hash": arrays.dataset_hash,
        "parametrization": arrays.parametrization,
        "parametrization_settings": arrays.parametrization_settings,
        "dataset": args.dataset,
    }
    if args.forward_only:  # the reversed copies are rebuilt there; here we check that they can be, bit for bit
        x = x[: arrays.n // 2]
        if arrays.n % 2 or not np.array_equal(
            reversed_rows(x, arrays.context["q_start"][: len(x)]), arrays.x[len(x) :]
        ):
            raise SystemExit(f"{args.task}: the second half of the arrays is not the reversed copies of the first")
        meta["forward_only"] = True
    args.out.parent.mkdir(parents=True, exist_ok=True)
    ctx = {f"context_{k}": v for k, v in arrays.context.items()}
    np.savez(args.out, x=x, split=arrays.split, meta=np.array(json.dumps(meta)), **ctx)
    print(f"{args.out}: {arrays.n} paths, {args.out.stat().st_size / 2**20:.1f} MiB, dataset {arrays.dataset_hash}")
    return 0


def reversed_rows(x, q_start):
    """The free rows of the reversed copies of paths with an end-effector goal, from their forward free rows: the
    full control points are the start three times, the free rows, the final configuration twice more
    (mpd.trajectory.bspline: free rows 3 .. n-3), and a clamped B-spline reversed in time is its control points in
    reverse order (mpd.data.dataset)."""
    import numpy as np

    full = np.concatenate([np.repeat(q_start[:, None], 3, 1), x, np.repeat(x[:, -1:], 2, 1)], 1)
    return np.ascontiguousarray(full[:, ::-1][:, 3:-2])


def load_arrays(path: Path):
    import numpy as np

    from mpd.models.data import TrainingArrays

    with np.load(path) as f:
        meta = json.loads(str(f["meta"]))
        ctx = {k[len("context_") :]: f[k] for k in f.files if k.startswith("context_")}
        x, split = f["x"], f["split"]
    if meta.pop("forward_only", False):
        x = np.concatenate([x, reversed_rows(x, ctx["q_start"][: len(x)])])
    if hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest() != meta.pop("x_sha256"):
        raise SystemExit(f"{path}: the rebuilt control points differ from the exported ones (sha256)")
    meta.pop("dataset", None)
    return TrainingArrays(x=x, context=ctx, split=split, **meta)


def flat(shipped_file: Path, out: Path) -> Path:
    """Move a shipped file and its lock (``<root>/models/<task>/``) to ``out`` itself: a device call brings back the
    files of its output folder only a few levels deep (the run of 2026-12-04 left a shipped prior out that way);
    `mpd/priors/models/<task>/` is where they go here."""
    out.mkdir(parents=True, exist_ok=True)
    lock = shipped_file.with_name(shipped_file.name.removesuffix(".pt") + ".lock.json")
    moved = out / shipped_file.name
    shutil.move(shipped_file, moved)
    shutil.move(lock, out / lock.name)
    shutil.rmtree(shipped_file.parents[2], ignore_errors=True)
    return moved


def fit_steps(rate: float, seconds_left: float) -> int:
    """The largest multiple of 1000 steps that ends before the deadline at SAFETY x the measured rate (0: none)."""
    return int(max(0.0, rate * SAFETY * (seconds_left - MARGIN_S)) // 1000 * 1000)


def train(args) -> int:
    import torch

    from mpd.models import shipped
    from mpd.models.train import train_model
    from mpd.tasks import load_task

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    arrays = load_arrays(args.arrays)
    task = load_task(arrays.task_name)
    base = task.training(args.profile)
    model_spec = task.model(args.profile)
    cache = Path(tempfile.mkdtemp(prefix="mpd-gpu-train-"))
    summary = {"task": task.name, "profile": args.profile, "device": device, "n_paths": arrays.n}
    if device.startswith("cuda"):
        summary["gpu"] = torch.cuda.get_device_name(device)

    def probe(n: int) -> tuple[float, float]:
        """Seconds of the training loop and of the whole call, for an n-step run."""
        spec = dataclasses.replace(base, steps=n, val_every=n, checkpoint_every=n)
        t = time.perf_counter()
        folder = cache / f"probe-{n}"
        path = train_model(
            arrays, args.kind, model_spec, spec, device=device, progress=False, cache=folder, shipped=False
        )
        return n / json.loads((Path(path).parent / "meta.json").read_text())["steps_per_s"], time.perf_counter() - t

    n = args.probe_steps
    try:  # on CUDA the step is captured in a CUDA graph (mpd.models.cuda_graph); should that fail, train eagerly
        short = probe(n)
    except Exception as e:  # noqa: BLE001 - a GPU's minutes are better spent on an eager run than on nothing
        if os.environ.get("MPD_CUDA_GRAPH") == "0" or not device.startswith("cuda"):
            raise
        summary["cuda_graph_error"] = f"{type(e).__name__}: {e}"[:2000]
        print(f"captured probe failed ({summary['cuda_graph_error'][:300]}); training eagerly", flush=True)
        os.environ["MPD_CUDA_GRAPH"] = "0"
        shutil.rmtree(cache / f"probe-{n}", ignore_errors=True)
        short = probe(n)
    # the rate from the difference of two probes: a run's fixed costs (the capture, the first eager steps, the data
    # moved to the device) made a single 200-step probe read 38 steps/s on an H200 that then trained at 54
    long = probe(3 * n)
    rate = 2 * n / max(long[0] - short[0], 1e-9)
    setup_s = max(0.0, short[1] - n / rate)
    left = args.deadline - time.time() - setup_s
    steps = min(args.max_steps, fit_steps(rate, left)) if args.steps is None else args.steps
    summary.update(
        probe_steps_per_s=round(rate, 2),
        probe_setup_s=round(setup_s, 1),
        seconds_left_after_probe=round(left, 1),
        steps=steps,
    )
    print(f"{task.name}: probe {rate:.1f} steps/s, {left:.0f} s left -> {steps} steps", flush=True)
    if steps < 1000 and args.steps is None:
        summary["error"] = "too little time left for 1000 steps"
    else:
        spec = dataclasses.replace(base, steps=steps)
        t = time.perf_counter()
        path = train_model(
            arrays, args.kind, model_spec, spec, device=device, progress=False, cache=cache, shipped=False
        )
        wall = time.perf_counter() - t
        meta = json.loads((Path(path).parent / "meta.json").read_text())
        out_file = flat(shipped.ship(path, args.out / "ship", weights_dtype="bfloat16"), args.out)
        shutil.copy(Path(path).parent / "meta.json", args.out / f"{out_file.stem}.meta.json")
        summary.update(
            identity=meta.get("identity"),
            cuda_graph=bool(meta.get("cuda_graph", False)),
            wall_s=round(wall, 1),
            steps_per_s=meta.get("steps_per_s"),
            final_train_loss=meta.get("final_train_loss"),
            final_val_loss=meta.get("final_val_loss"),
            training_spec=dataclasses.asdict(spec),
            shipped=str(out_file.relative_to(args.out)),
        )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"train-{task.name}.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps({k: v for k, v in summary.items() if k != "training_spec"}), flush=True)
    return 0 if "error" not in summary else 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="write a task's training arrays to one .npz")
    e.add_argument("task")
    e.add_argument("--dataset", required=True)
    e.add_argument("--parametrization", default="bspline", choices=["bspline", "waypoints"])
    e.add_argument("--out", type=Path, required=True)
    e.add_argument("--forward-only", action="store_true", help="store the forward paths only (about half the size)")
    t = sub.add_parser("train", help="train from exported arrays before a deadline, ship the result under --out")
    t.add_argument("arrays", type=Path)
    t.add_argument("--profile", default="gpu")
    t.add_argument("--kind", default="diffusion", choices=["diffusion", "cvae"])
    t.add_argument("--deadline", type=float, required=True, help="seconds since the epoch")
    t.add_argument("--steps", type=int, default=None, help="fixed steps instead of fitting them to the deadline")
    t.add_argument("--max-steps", type=int, default=100_000)
    t.add_argument("--probe-steps", type=int, default=PROBE_STEPS)
    t.add_argument("--device", default=None)
    t.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    return export(args) if args.cmd == "export" else train(args)


if __name__ == "__main__":
    sys.exit(main())
