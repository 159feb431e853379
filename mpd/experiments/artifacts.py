"""The artifact store as the runner sees it: for every task of a spec, its dataset, its evaluation contexts and the
models its cells need, built only when missing (content-addressed by their inputs: a second run reuses them)."""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpd.data.eval_contexts import ContextSet
from mpd.executor import imap, threads
from mpd.models.data import training_arrays
from mpd.schema import file_sha256
from mpd.tasks import Task, load_task

# rough rates (planned contexts per second per core), only for the dry run's estimate; the Panda's from the
# Warehouse benchmark with the compiled checker (16 /s; Spheres3D runs at ~45 /s)
_PATHS_PER_S = {
    "RobotPointMass2D": 60.0,
    "RobotPlanar2Link": 20.0,
    "RobotPlanar4Link": 8.0,
    "RobotPanda": 15.0,
}
# training steps/s by U-Net depth, one thread per model on a 2-core CPU at the cpu profiles' batch sizes: measured
# 8.4-10.8/s for the (1, 2, 4) nets at batch 128 (two bf16 models side by side, reports/recipe-study-2d; fp32 is within
# 5 % at 1 thread), ~2/s for the (1, 2, 4, 8) nets at batch 512
_STEPS_PER_S = {2: 12.0, 3: 9.5, 4: 2.0}


@dataclass
class Need:
    kind: str  # dataset | model | contexts
    task: str
    name: str
    exists: bool
    detail: str = ""
    estimate_s: float = 0.0

    def describe(self) -> str:
        if self.exists:
            state = {
                "shipped": "ready (shipped prior)",
                "digest": "not needed: its shipped digest has the contexts and range, and every model is ready",
            }.get(self.detail, "ready")
        else:
            state = f"to build ({self.detail}, ~{self.estimate_s / 60:.1f} min)"
        return f"{self.kind:8s} {self.task}: {self.name}: {state}"


@dataclass
class ModelArtifact:
    kind: str
    parametrization: str
    identity: str
    path: Path
    sha256: str
    steps: int = 0
    wall_time_s: float = 0.0  # training wall time, stable-phase trunk included (the cost of this model alone)
    training: tuple = ()  # the spec's training overrides that made it
    # where the run got it: "cache" (there before the run), "shipped" (a verified shipped prior, mpd/priors) or
    # "trained" (trained by this run)
    source: str = "trained"


@dataclass
class TaskArtifacts:
    task_name: str
    task_hash: str
    dataset_id: str
    dataset_hash: str
    contexts: dict[str, ContextSet]  # per scene (mpd.data.eval_contexts.scene_name)
    # (lo, hi) per joint of the training split's free B-spline control points: the normalized space of the
    # planners without a model, as the authors' baselines use the dataset's normalizer
    data_range: tuple[list[float], list[float]] | None = None
    # (kind, parametrization, training overrides) -> model
    models: dict[tuple[str, str, tuple], ModelArtifact] = field(default_factory=dict)
    # where the run got the dataset: "cache", "generated" (by this run) or "digest" (not generated: its shipped
    # digest gave the contexts and the range, every model being in the cache or shipped; mpd.data.digest)
    dataset_source: str = "cache"

    def contexts_for(self, params: dict) -> ContextSet:
        from mpd.data.eval_contexts import scene_name

        return self.contexts[scene_name(bool(params["extra_objects"]), float(params["rotation_deg"] or 0.0))]

    def model_for(self, method: str, parametrization: str, training: tuple = ()) -> ModelArtifact | None:
        from mpd.planners import get_planner_class

        kind = get_planner_class(method).model_kind
        return None if kind is None else self.models[(kind, parametrization, tuple(training))]

    def summary(self) -> dict:
        return {
            "task_hash": self.task_hash,
            "dataset_id": self.dataset_id,
            "dataset_hash": self.dataset_hash,
            "dataset_source": self.dataset_source,
            "models": {_model_label(k, p, tr): m.identity for (k, p, tr), m in self.models.items()},
            "model_sources": {_model_label(k, p, tr): m.source for (k, p, tr), m in self.models.items()},
            "contexts": {
                scene: {
                    "sha256": cs.hash,
                    "source": cs.meta.get("source"),
                    "n_contexts": len(cs),
                    "n_skipped": cs.meta.get("n_skipped", 0),
                    "skipped_index": cs.meta.get("skipped_index", []),
                    "context_seed": cs.meta.get("context_seed"),
                }
                for scene, cs in sorted(self.contexts.items())
            },
        }


def _model_label(kind: str, parametrization: str, training: tuple) -> str:
    extra = "".join(f",{k}={v}" for k, v in training)
    return f"{kind}-{parametrization}" + (f"[{extra[1:]}]" if extra else "")


def _model_kinds(cells, task_name: str) -> set[tuple[str, str, tuple]]:
    from mpd.planners import get_planner_class

    out = set()
    for c in cells:
        p = c.p
        if p["task"] != task_name:
            continue
        kind = get_planner_class(p["method"]).model_kind
        if kind is not None:
            out.add((kind, p["parametrization"] or "bspline", c.training_overrides()))
    return out


def model_settings(task: Task, overrides: tuple = (), profile: str | None = None):
    """The network of the task's training ``profile`` (its ``[model]`` with the profile's changes) with a cell's
    ``model.*`` values."""
    from mpd.experiments.spec import MODEL_PREFIX

    base = task.model(profile)
    mine = {k[len(MODEL_PREFIX) :]: v for k, v in overrides if k.startswith(MODEL_PREFIX)}
    return dataclasses.replace(base, **mine) if mine else base


def training_settings(task: Task, ts, overrides: tuple = (), kind: str = "diffusion", par: str | None = None):
    """The task's training profile of the spec for a model of ``kind`` and parametrization ``par``, with the spec's
    step count (``train_steps``, the task's or the model's) and a cell's ``training.*`` values (its ``model.*``
    values are the network's: `model_settings`)."""
    from mpd.experiments.spec import MODEL_PREFIX

    overrides = tuple((k, v) for k, v in overrides if not k.startswith(MODEL_PREFIX))
    spec = task.training(ts.profile_for(kind, par))
    steps = ts.steps_for(kind, par)
    if steps is not None:
        spec = dataclasses.replace(
            spec,
            steps=steps,
            checkpoint_every=min(spec.checkpoint_every, steps),
            val_every=min(spec.val_every, steps),
        )
    return dataclasses.replace(spec, **dict(overrides)) if overrides else spec


def data_range(task: Task, dataset) -> tuple[list[float], list[float]]:
    """Per-joint (lo, hi) of the free B-spline control points of the training split (the models' range)."""
    from mpd.data.dataset import SPLITS

    x = training_arrays(task, dataset, "bspline")
    train = x.x[x.split == SPLITS.index("train")].reshape(-1, task.dof).astype(np.float64)
    return train.min(0).tolist(), train.max(0).tolist()


def _model_identity(task: Task, ts, content_hash: str, kind: str, par: str, training: tuple) -> str:
    """A model's identity from the dataset's content hash alone (no dataset loaded)."""
    from mpd.models.train import model_identity
    from mpd.trajectory import make_parametrization

    settings = make_parametrization(task, par).settings()
    return model_identity(
        content_hash,
        kind,
        par,
        settings,
        model_settings(task, training, ts.profile_for(kind, par)),
        training_settings(task, ts, training, kind, par),
        0,
    )


def _available(task_name: str, kind: str, par: str, ident: str) -> str | None:
    """Where the model of this identity is without training: "cache", "shipped" (a verified shipped prior, which
    train_model installs) or None."""
    from mpd.models import shipped
    from mpd.models.train import model_dir

    if (model_dir(task_name, kind, par, ident) / "model.pt").is_file():
        return "cache"
    return "shipped" if shipped.find(task_name, kind, par, ident) is not None else None


def _job_identity(job) -> str:
    from mpd.models.train import model_identity

    _, kind, par, arrays, ms, ts, _ = job
    return model_identity(arrays.dataset_hash, kind, par, arrays.parametrization_settings, ms, ts, 0)


def _ready_model(task: Task, ts, content_hash: str, key: tuple) -> tuple[str, str] | None:
    """(identity, "cache" | "shipped") when the model of ``key`` needs no training, else None."""
    kind, par, tr = key
    ident = _model_identity(task, ts, content_hash, kind, par, tr)
    where = _available(task.name, kind, par, ident)
    return (ident, where) if where else None


def _digest_if_enough(task: Task, ts, rd, keys) -> tuple | None:
    """(digest, {key: (identity, source)}) when the dataset is not generated here but its shipped digest and the
    models make it unnecessary; else None."""
    from mpd.data import digest
    from mpd.data.generate import committed_content_hash

    dg = digest.find(task.name, rd.name, committed_content_hash(rd))
    if dg is None:
        return None
    ready = {k: _ready_model(task, ts, dg.info["content_hash"], k) for k in keys}
    return (dg, ready) if all(ready.values()) else None


def needs(spec, cells) -> list[Need]:
    """What each task of the spec needs, and whether it exists (for the dry run)."""
    from mpd.data.generate import chunk_states, committed_content_hash, committed_lock

    out = []
    for task_name in sorted({c.p["task"] for c in cells}):
        task = load_task(spec.task_file(task_name))
        ts = spec.data.tasks[task_name]
        rd = spec.definition(task_name)
        bad = chunk_states(rd)
        n = rd.definition.n_contexts
        # a committed lock says what the generation cost (its CPU seconds, on two cores here); else a rough rate
        core_s = ((committed_lock(rd) or {}).get("figures") or {}).get("core_seconds")
        gen_s = core_s / 2 if core_s else n / (_PATHS_PER_S.get(task.robot.name, 2.0) * 2)
        keys = sorted(_model_kinds(cells, task_name), key=repr)
        via_digest = _digest_if_enough(task, ts, rd, keys) if bad else None
        if via_digest:
            out.append(Need("dataset", task_name, f"{rd.name} [{rd.identity}]", True, "digest"))
        else:
            out.append(Need("dataset", task_name, f"{rd.name} [{rd.identity}]", not bad, f"plan {n} contexts", gen_s))
        # without the dataset here, the committed lock says what its content hash will be (generation is byte for
        # byte reproducible), so the models' identities are known before it is generated
        content = _content_hash(rd) if not bad else committed_content_hash(rd)
        for key in keys:
            kind, par, tr = key
            train = training_settings(task, ts, tr, kind, par)
            steps_s = _STEPS_PER_S.get(len(model_settings(task, tr, ts.profile_for(kind, par)).unet_dim_mults), 2.0)
            if content is None:
                out.append(
                    Need(
                        "model",
                        task_name,
                        f"{_model_label(kind, par, tr)} (after the dataset)",
                        False,
                        f"train {train.steps} steps",
                        train.steps / steps_s,
                    )
                )
                continue
            ready = _ready_model(task, ts, content, key)
            ident = ready[0] if ready else _model_identity(task, ts, content, kind, par, tr)
            label = f"{_model_label(kind, par, tr)} [{ident}]"
            if ready:
                out.append(Need("model", task_name, label, True, ready[1]))
            else:
                out.append(Need("model", task_name, label, False, f"train {train.steps} steps", train.steps / steps_s))
    return out


def _content_hash(rd) -> str | None:
    p = rd.data_dir / "lock.json"
    return json.loads(p.read_text()).get("content_hash") if p.exists() else None


def resolve(
    spec, cells, progress: bool = True, workers: int = 1, executor: str = "local", address: str | None = None
) -> dict[str, TaskArtifacts]:
    """Datasets, evaluation contexts and models of every task of the cells, generated/trained when missing (with
    ``executor="ray"``: dataset chunks and trainings as Ray tasks on the cluster at ``address``)."""
    from mpd.data import eval_contexts as ec
    from mpd.data.dataset import load_dataset
    from mpd.data.generate import chunk_states
    from mpd.models import shipped
    from mpd.models.train import model_dir

    out, jobs = {}, []
    for task_name in sorted({c.p["task"] for c in cells}):
        task = load_task(spec.task_file(task_name))
        ts = spec.data.tasks[task_name]
        # wsd budgets of one recipe in increasing steps, so that each resumes from the stable phase of the one before
        keys = sorted(_model_kinds(cells, task_name), key=lambda k: (repr(k[:2]), _steps_last(k[2])))
        rd = spec.definition(task_name)
        missing = bool(chunk_states(rd))
        via_digest = _digest_if_enough(task, ts, rd, keys) if missing else None
        if via_digest:
            data, ready = via_digest
            if progress:
                print(
                    f"{task_name}: dataset {rd.name} not generated: its shipped digest and models suffice",
                    file=sys.stderr,
                )
        else:
            # a run writes only the cache (create_lock=False)
            data = load_dataset(rd, progress=progress, create_lock=False, executor=executor, address=address)
            if data.info.get("synthetic"):
                raise ValueError(f"{task_name}: dataset {rd.name} is SYNTHETIC (random paths): never used by a run")
        n_ctx = ts.n_contexts or spec.data.n_contexts
        scenes = sorted(
            {(bool(c.p["extra_objects"]), float(c.p["rotation_deg"] or 0.0)) for c in cells if c.p["task"] == task_name}
        )
        if ts.contexts == "held-out":
            base = ec.task_contexts(task, data, n_ctx, spec.data.context_seed)
            contexts = {ec.scene_name(*sc): ec.for_scene(base, task, *sc, turn=ts.turn_contexts) for sc in scenes}
        else:
            contexts = {ec.scene_name(*sc): ec.sampled_contexts(task, n_ctx, *sc) for sc in scenes}
        out[task_name] = TaskArtifacts(
            task.name,
            task.file_hash,
            data.info["identity"],
            data.info["content_hash"],
            contexts,
            data_range=data.data_range if via_digest else data_range(task, data),
            dataset_source="digest" if via_digest else ("generated" if missing else "cache"),
        )
        if via_digest:
            for key, (ident, source) in ready.items():
                kind, par, tr = key
                d = model_dir(task_name, kind, par, ident)
                path = d / "model.pt" if source == "cache" else shipped.install(task_name, kind, par, ident, d)
                if path is None:  # the shipped file changed since it was checked
                    raise RuntimeError(f"{task_name}: shipped prior {kind}-{par} [{ident}] could not be installed")
                out[task_name].models[key] = _artifact(path, key, source)
            continue
        arrays = {}
        for kind, par, tr in keys:
            if par not in arrays:
                arrays[par] = training_arrays(task, data, par)
            jobs.append(
                (
                    task_name,
                    kind,
                    par,
                    arrays[par],
                    model_settings(task, tr, ts.profile_for(kind, par)),
                    training_settings(task, ts, tr, kind, par),
                    tr,
                )
            )
    before = [_in_cache(j) for j in jobs]
    paths = train_models(jobs, workers, progress, executor, address)
    for (task_name, kind, par, *_, tr), path, cached in zip(jobs, paths, before):
        out[task_name].models[(kind, par, tr)] = _artifact(path, (kind, par, tr), "cache" if cached else None)
    return out


def _artifact(path: Path, key: tuple, source: str | None) -> ModelArtifact:
    kind, par, tr = key
    meta = json.loads((path.parent / "meta.json").read_text())
    source = source or meta.get("source", "trained")
    return ModelArtifact(
        kind, par, meta["identity"], path, file_sha256(path), int(meta["step"]), float(meta["wall_time_s"]), tr,
        source,
    )  # fmt: skip


def _in_cache(job) -> bool:
    from mpd.models.train import model_dir

    task_name, kind, par, *_ = job
    return (model_dir(task_name, kind, par, _job_identity(job)) / "model.pt").is_file()


def _steps_last(training: tuple) -> tuple:
    d = dict(training)
    return (repr(sorted((k, v) for k, v in d.items() if k != "steps")), d.get("steps", 0))


# Intra-op threads of every training a spec run makes, whatever the executor (this process, a worker process, a Ray
# task): a CPU training's bits depend on the thread count (the reductions' split), so one count for all keeps "a
# model's identity decides its weights" true across executors on one CPU type (tests/test_ray_cluster.py).
TRAIN_THREADS = 1


def _train_job(job, progress: bool) -> Path:
    from mpd.models.train import train_model

    with threads(TRAIN_THREADS):
        _, kind, _, arrays, model_spec, train_spec, _ = job
        return Path(train_model(arrays, kind, model_spec, train_spec, seed=0, progress=progress))


def _train_chain(chain: list, progress: bool) -> list[Path]:
    return [_train_job(j, progress) for j in chain]


def _chain_name(item: tuple) -> str:
    return "the training of " + ", ".join(f"{j[0]} {_model_label(j[1], j[2], j[6])}" for j in item[0])


def _chain_key(job) -> tuple:
    """Jobs of one key train one after the other in one process: the wsd budgets of one recipe and one network
    (shortest first, each resuming from the stable phase of the one before); every other job is a chain of its own.
    The network's settings are part of the key: two widths share no trunk, so they train in parallel."""
    task_name, kind, par, _, model_spec, ts, _ = job
    if ts.lr_schedule != "wsd":
        return (id(job),)
    rest = {k: v for k, v in dataclasses.asdict(ts).items() if k not in ("steps", "decay_fraction")}
    return (task_name, kind, par, repr(model_spec), repr(sorted(rest.items())))


def train_models(
    jobs: list, workers: int, progress: bool, executor: str = "local", address: str | None = None
) -> list[Path]:
    """Train the missing models, several at once (one process and one thread each) when workers allow: on a small
    CPU two single-threaded trainings finish in about the time of one two-threaded training. The wsd budgets of one
    recipe form a chain that runs in one worker, in increasing steps. ``executor="ray"``: each chain is a Ray task
    (one GPU when the cluster has GPUs, else one CPU), retried by Ray when its worker dies (it resumes from the
    worker's ``last.pt``); the models come back through the object store, checked by sha256 on arrival."""

    def exists(job) -> bool:  # in the cache, or a shipped prior that train_model will install without training
        return _available(job[0], job[1], job[2], _job_identity(job)) is not None

    chains: dict[tuple, list] = {}
    for j in sorted((j for j in jobs if not exists(j)), key=lambda j: j[5].steps):
        chains.setdefault(_chain_key(j), []).append(j)
    done: dict[int, Path] = {}
    if executor == "ray" and chains:
        _train_ray(list(chains.values()), address)
    elif chains:
        n = min(max(1, workers), len(chains))
        items = [(chain, progress) for chain in chains.values()]
        mode = "process" if n > 1 else "serial"
        for (chain, _), paths in imap(_train_chain, items, mode, n, threads=TRAIN_THREADS, name=_chain_name):
            done.update(zip(map(id, chain), paths))
    # the others are in the cache now, or a shipped prior that train_model installs: each returns at once
    return [done[id(j)] if id(j) in done else _train_job(j, progress) for j in jobs]


def _ray_chain(chain: list) -> list[dict]:
    """Ray task: train a chain of models in this worker's cache; return each model's files for the driver."""
    import os

    from mpd import distributed

    out = []
    for job, path in zip(chain, _train_chain(chain, False)):
        meta = json.loads((path.parent / "meta.json").read_text())
        meta["node"] = distributed.node_id()
        # recorded here too: on a shared cache the driver finds this very file and writes nothing
        tmp = path.parent / f".meta.json.node-{os.getpid()}"
        tmp.write_text(json.dumps(meta, indent=2, sort_keys=True))
        os.replace(tmp, path.parent / "meta.json")
        data = path.read_bytes()
        out.append(
            {"task": job[0], "identity": meta["identity"], "model": data, "meta": meta, "sha256": file_sha256(path)}
        )
    return out


def _train_ray(chains: list[list], address: str | None = None) -> None:
    """Every chain as a Ray task; each finished model is written into this process's cache (unless it already holds
    that very file: a shared cache), after its sha256 is checked."""
    import os

    from mpd import distributed
    from mpd.models.train import model_dir

    distributed.init(address)
    gpu = distributed.cluster_gpus() > 0
    options = {"num_gpus": 1 if gpu else 0, "num_cpus": 0 if gpu else 1}
    for _, models in imap(_ray_chain, [(chain,) for chain in chains], "ray", ray_options=options, name=_chain_name):
        for m in models:
            data = distributed.checked(m["model"], m["sha256"], f"model {m['identity']}")
            meta = m["meta"]
            d = model_dir(m["task"], meta["kind"], meta["parametrization"], m["identity"])
            if (d / "model.pt").is_file() and file_sha256(d / "model.pt") == m["sha256"]:
                continue
            d.mkdir(parents=True, exist_ok=True)
            for name, blob in (("meta.json", json.dumps(meta, indent=2, sort_keys=True).encode()), ("model.pt", data)):
                tmp = d / f".{name}.ray-{os.getpid()}"
                tmp.write_bytes(blob)
                os.replace(tmp, d / name)  # meta first: a model.pt always has its meta.json
