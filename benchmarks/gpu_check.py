"""The prepared GPU check: everything a CUDA machine should tell us, in one command and within 10 minutes.

On a machine with CUDA it runs the CUDA tests (they skip on a CPU), the plan and network benchmarks on the GPU, a
short training, and writes one JSON summary. Every section is timed and guarded: one that fails records its error
and the others still run. It runs on a CPU too (``--device cpu --quick``, tested in ``tests/test_gpu_check.py``),
so the command is known to work before it runs on a GPU.

With internet (any CUDA machine):   nox -s gpu                 (installs mpd, then runs this)
An offline GPU machine (its python3 has a CUDA torch): prepare the wheels here once, `nox -s gpu_wheels` (mpd's
dependencies that image lacks, for its Python 3.12, into `.whl/`), then in one device call that carries `.whl`:

    python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site:$PWD/.whl:$PWD
    python3 benchmarks/gpu_check.py --out $OUT/gpu.json

(`.whl/pybullet_data` holds the Panda URDF, which mpd reads from pybullet_data, for that machine has no pybullet.)
It took 65 s on an H200 on 2026-12-04 (benchmarks/results/2026-12-04-h200-gpu-check.json). The rest of a GPU's time can
train a prior: benchmarks/gpu_train.py.

Sections: ``environment`` (torch, CUDA, device, capability), ``cuda_tests`` (pytest -k cuda: passed / failed /
skipped), ``plans`` (MPD and prior-only plans of 100 trajectories, EnvSpheres3D with the Panda-sized network and
EnvSimple2D, random weights of the configs' sizes: median wall time and breakdown), ``network`` (forward of 100 and
training steps/s at batch 512, fp32 and bf16 autocast), ``training`` (a short real `train_model` on the device, its
loss and steps/s, the checkpoint loaded back on the CPU), ``graphed_training`` (steps/s of the Panda-sized network's
training step captured in a CUDA graph, batch 512 / 1024 / 2048, bf16 and fp32).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run as a script from any folder: mpd from this checkout


def _sync(device) -> None:
    import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def _median_time(fn, device, rounds: int, warmup: int = 1) -> tuple[float, list[float]]:
    for _ in range(warmup):
        fn()
    _sync(device)
    times = []
    for _ in range(rounds):
        t = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t)
    return statistics.median(times), times


def environment(device: str) -> dict:
    import torch

    from mpd.provenance import cpu_model, git_state

    out = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda_available": torch.cuda.is_available(),
        "torch_cuda": torch.version.cuda,
        "device": device,
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "git_commit": git_state()[0],
    }
    if torch.device(device).type == "cuda":
        p = torch.cuda.get_device_properties(device)
        out.update(gpu=p.name, capability=f"{p.major}.{p.minor}", gpu_memory_gib=round(p.total_memory / 2**30, 1))
    return out


def cuda_tests(quick: bool) -> dict:
    xml = Path(tempfile.mkdtemp()) / "junit.xml"
    cmd = [sys.executable, "-m", "pytest", "-q", "-k", "cuda", "-p", "no:cacheprovider", f"--junitxml={xml}"]
    cmd += ["--continue-on-collection-errors"]  # a module that needs what the machine lacks (pybullet) is no reason
    cmd += ["tests/test_robots.py"] if quick else ["tests"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    suite = ET.parse(xml).getroot()
    suite = suite if suite.tag == "testsuite" else suite[0]
    n = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    return {
        "exit_code": proc.returncode,
        "passed": n["tests"] - n["failures"] - n["errors"] - n["skipped"],
        "failed": n["failures"] + n["errors"],
        "skipped": n["skipped"],
        "tail": proc.stdout[-2000:],
    }


def random_model(task, param):
    """A diffusion prior of the task's network sizes with random (seeded) weights: timing does not depend on them."""
    import torch

    from mpd.models.checkpoint import LoadedModel, build_network
    from mpd.models.normalizer import Normalizer

    kind = "goal_ee_pose" if task.ee_goal else "goal_joint_position"
    torch.manual_seed(0)
    net = build_network("diffusion", task.dof, param.n_free, kind, task.spec.model).eval()
    lo, hi = task.robot.q_min.float(), task.robot.q_max.float()
    norms = {"q_start": Normalizer(lo, hi)}
    norms.update(
        {"ee_pos": Normalizer(-torch.ones(3), torch.ones(3))} if task.ee_goal else {"q_goal": Normalizer(lo, hi)}
    )
    meta = {
        "task_name": task.name,
        "parametrization": "bspline",
        "horizon": param.n_free,
        "dof": task.dof,
        "context_kind": kind,
    }
    return LoadedModel("diffusion", net.requires_grad_(False), Normalizer(lo, hi), norms, meta, path="<random>")


def plan_context(task, device):
    """A fixed planning context of the task (an EE goal pose for the Panda, a joint goal for the 2-D tasks)."""
    import torch

    from mpd.planners import Context

    if task.ee_goal:
        qs = torch.tensor([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
        p, r = task.robot.ee_pose(torch.tensor([0.5, 0.3, -0.4, -2.0, 0.2, 2.0, 0.5], dtype=torch.float64))
        return Context(qs, None, p.float(), r.float())
    return Context(torch.tensor([-0.8, -0.8]), torch.tensor([0.8, 0.8]), None, None)


def plans(device: str, rounds: int, quick: bool = False) -> dict:
    from mpd.planners import make_planner
    from mpd.tasks import load_task
    from mpd.trajectory import make_parametrization

    out = {}
    tasks = ("EnvSpheres3D-RobotPanda", "EnvSimple2D-RobotPointMass2D")
    for task_name in tasks[1:] if quick else tasks:
        task = load_task(task_name)
        param = make_parametrization(task)
        model = random_model(task, param)
        ctx = plan_context(task, device)
        for method in ("mpd", "dprior"):
            planner = make_planner(method, task, model=model, device=device, extra_objects=True)
            timings = []

            def run(planner=planner, timings=timings, ctx=ctx):
                timings.append(planner.plan(ctx, 100, seed=0).timings)

            med, times = _median_time(run, device, rounds, warmup=0 if quick else 1)
            t = timings[len(timings) // 2]
            out[f"{method}/{task_name}"] = {
                "median_s": round(med, 4),
                "rounds_s": [round(x, 4) for x in times],
                "breakdown": {k: round(float(v), 4) for k, v in t.items()},
            }
    return out


def panda_batch(dof: int, n: int, generator, device: str):
    """n random normalized Panda training samples (24 free control points) and their contexts, drawn on the CPU
    generator and moved to ``device``: the network sections' inputs (timing does not depend on the values)."""
    import torch

    x = (torch.rand(n, 24, dof, generator=generator) * 2 - 1).to(device)
    ctx = {
        "q_start": (torch.rand(n, dof, generator=generator) * 2 - 1).to(device),
        "ee_pos": torch.rand(n, 3, generator=generator).to(device),
        "ee_rot": torch.linalg.qr(torch.randn(n, 3, 3, generator=generator)).Q.to(device),
    }
    return x, ctx


def network(device: str, rounds: int, train_batch: int = 512) -> dict:
    import torch

    from mpd.models.diffusion import DiffusionModel
    from mpd.tasks import load_task

    task = load_task("EnvSpheres3D-RobotPanda")
    torch.manual_seed(0)
    model = DiffusionModel(task.dof, 24, "goal_ee_pose", task.spec.model).to(device)
    out = {"parameters": sum(p.numel() for p in model.parameters())}
    g = torch.Generator(device="cpu").manual_seed(0)

    def batch(n):
        return panda_batch(task.dof, n, g, device)

    x, ctx = batch(100)
    model.eval()
    for precision in ("fp32", "bf16"):
        autocast = torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=precision == "bf16")

        def fwd(autocast=autocast):
            with torch.no_grad(), autocast:
                model(x, 50, ctx)

        med, _ = _median_time(fwd, device, rounds * 4, warmup=2)
        out[f"forward_batch100_{precision}_ms"] = round(1e3 * med, 3)
    model.train()
    from mpd.models.train import make_optimizer
    from mpd.tasks.spec import TrainingSpec

    opt = make_optimizer(model, TrainingSpec(batch_size=train_batch, steps=1))
    xb, cb = batch(train_batch)
    gen = torch.Generator(device=device).manual_seed(0)
    for precision in ("fp32", "bf16"):
        autocast = torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=precision == "bf16")

        def step(autocast=autocast):
            with autocast:
                loss = model.loss(xb, cb, gen)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()

        med, _ = _median_time(step, device, rounds * 2, warmup=2)
        out[f"train_steps_per_s_batch{train_batch}_{precision}"] = round(1.0 / med, 2)
    return out


def graphed_training(device: str, batches=(512, 1024, 2048), steps: int = 100) -> dict:
    """Training steps/s of the Panda-sized network with the step captured in a CUDA graph
    (mpd.models.cuda_graph.GraphedStep, as train_model runs it on CUDA), per batch size and precision."""
    import copy

    import torch

    from mpd.device import resolve
    from mpd.models.cuda_graph import GraphedStep
    from mpd.models.diffusion import DiffusionModel
    from mpd.models.train import make_optimizer
    from mpd.tasks import load_task
    from mpd.tasks.spec import TrainingSpec

    if torch.device(device).type != "cuda":
        return {"skipped": "no CUDA device"}
    task = load_task("EnvSpheres3D-RobotPanda")
    n = 8192
    x, ctx = panda_batch(task.dof, n, torch.Generator(device="cpu").manual_seed(0), device)
    g = torch.Generator(device=device).manual_seed(0)  # the training's draws, on the device (captured)
    out = {}
    for precision in ("bf16", "fp32"):
        for b in batches:
            torch.manual_seed(0)
            net = DiffusionModel(task.dof, 24, "goal_ee_pose", task.spec.model).to(device).train()
            ema = copy.deepcopy(net).requires_grad_(False)
            ts = TrainingSpec(batch_size=b, steps=steps, lr=1e-3, ema_start=0, ema_every=1)
            opt = make_optimizer(net, ts)
            running = torch.zeros((), device=device)

            def draw(b=b):
                idx = torch.randint(n, (b,), generator=g, device=device)
                return x[idx], {k: v[idx] for k, v in ctx.items()}

            step = GraphedStep("diffusion", net, ema, opt, g, ts, {}, resolve(device, precision), draw, running)
            for i in range(10):  # eager steps, the capture, replays
                step(i, 1e-3)
            _sync(device)
            t = time.perf_counter()
            for i in range(10, 10 + steps):
                step(i, 1e-3)
            _sync(device)
            out[f"steps_per_s_batch{b}_{precision}"] = round(steps / (time.perf_counter() - t), 1)
            out[f"loss_finite_batch{b}_{precision}"] = bool(torch.isfinite(running).item())
            del net, ema, opt, step
    return out


def training(device: str, steps: int, batch_size: int = 256) -> dict:
    import numpy as np
    import torch

    from mpd.models.checkpoint import load_model
    from mpd.models.data import TrainingArrays
    from mpd.models.train import train_model
    from mpd.tasks import load_task
    from mpd.tasks.spec import TrainingSpec

    task = load_task("EnvSimple2D-RobotPointMass2D")
    rng = np.random.default_rng(0)
    n, h = 4096, 24
    qs, qg = rng.uniform(-1, 1, (n, 2)), rng.uniform(-1, 1, (n, 2))
    s = np.linspace(0, 1, h + 2)[1:-1][None, :, None]
    x = qs[:, None] * (1 - s) + qg[:, None] * s + 0.3 * np.sin(np.pi * s) * rng.choice([-1.0, 1.0], (n, 1, 1))
    split = np.zeros(n, np.int8)
    split[-256:] = 1
    arrays = TrainingArrays(
        x=x.astype(np.float32),
        context={"q_start": qs.astype(np.float32), "q_goal": qg.astype(np.float32)},
        split=split,
        task_name="GpuCheck",
        task_hash="gpu-check",
        dataset_hash=f"gpu-check-{device}",
        parametrization="bspline",
    )
    spec = TrainingSpec(
        batch_size=batch_size, steps=steps, lr=3e-4, val_every=max(1, steps // 4), checkpoint_every=steps
    )
    cache = Path(tempfile.mkdtemp(prefix="mpd-gpu-check-"))
    t = time.perf_counter()
    path = train_model(arrays, "diffusion", task.spec.model, spec, device=device, progress=False, cache=cache)
    wall = time.perf_counter() - t
    meta = json.loads((Path(path).parent / "meta.json").read_text())
    back = load_model(path, device="cpu")
    return {
        "steps": steps,
        "wall_s": round(wall, 2),
        "steps_per_s": round(steps / wall, 2),
        "final_train_loss": meta.get("final_train_loss"),
        "final_val_loss": meta.get("final_val_loss"),
        "device_recorded": meta.get("device"),
        "loads_on_cpu": next(back.network.parameters()).device.type == "cpu",
        "finite": bool(np.isfinite(meta.get("final_train_loss") or np.nan)),
        "torch_threads": torch.get_num_threads(),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default=None, help="default: cuda when available, else cpu")
    ap.add_argument("--out", type=Path, default=REPO / ".benchmarks" / "gpu.json")
    ap.add_argument("--quick", action="store_true", help="fewer rounds and steps (the CPU test of this script)")
    ap.add_argument("--sections", nargs="+", default=None, help="run only these sections (environment always)")
    args = ap.parse_args()
    import torch

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cpu":
        torch.set_num_threads(min(2, os.cpu_count() or 1))
    rounds, steps = (1, 10) if args.quick else (5, 1000)
    sections = {
        "environment": lambda: environment(device),
        "cuda_tests": lambda: cuda_tests(args.quick),
        "plans": lambda: plans(device, rounds, args.quick),
        "network": lambda: network(device, rounds, 32 if args.quick else 512),
        "training": lambda: training(device, steps, 32 if args.quick else 256),
        "graphed_training": lambda: graphed_training(device, steps=20 if args.quick else 100),
    }
    if args.sections:
        unknown = set(args.sections) - set(sections)
        if unknown:
            ap.error(f"--sections: unknown {sorted(unknown)} (known: {', '.join(sections)})")
        sections = {k: v for k, v in sections.items() if k in args.sections or k == "environment"}
    summary: dict = {"format": "mpd-gpu-check", "quick": args.quick}
    t0 = time.perf_counter()
    for name, fn in sections.items():
        t = time.perf_counter()
        try:
            summary[name] = fn()
        except Exception as e:  # one broken section must not cost the others
            summary[name] = {"error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()[-3000:]}
        summary.setdefault("section_s", {})[name] = round(time.perf_counter() - t, 1)
        print(f"{name}: {json.dumps(summary[name])[:400]}", file=sys.stderr, flush=True)
    summary["total_s"] = round(time.perf_counter() - t0, 1)
    summary["errors"] = [k for k in sections if isinstance(summary.get(k), dict) and "error" in summary[k]]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=1) + "\n")
    print(f"wrote {args.out} ({summary['total_s']} s; errors: {summary['errors'] or 'none'})", file=sys.stderr)
    return 1 if summary["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
