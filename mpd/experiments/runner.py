"""The runner: spec -> cells -> (dataset, model) artifacts -> units (cell x context) -> results, recordings.

A run lives in ``runs/<spec>-<spec hash>-<commit>`` (``$MPD_RUNS``): the same spec at the same commit reuses the
folder, so a re-run skips finished cells and an interrupted run resumes where it stopped. ``--fresh`` starts over.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from mpd.executor import imap
from mpd.experiments import artifacts
from mpd.experiments.results import RowStore, read_results, write_json, write_parquet
from mpd.experiments.spec import Cell, Spec
from mpd.experiments.units import Unit, UnitResult, run_unit
from mpd.paths import runs_dir
from mpd.planners.settings import fast_enabled
from mpd.provenance import cpu_model, git_state, provenance
from mpd.schema import file_sha256

log = logging.getLogger(__name__)


@dataclass
class Plan:
    """What a run will do: the cells, the artifacts they need, and the units still to compute."""

    cells: list[Cell]
    needs: list[artifacts.Need]
    units_total: int
    units_todo: int


def run_id(spec: Spec) -> str:
    commit, _ = git_state()
    return f"{spec.name}-{spec.hash[:8]}-{commit[:8]}"


def plan_seed(seed: int, context_index: int) -> int:
    # the same (seed, context) gets the same stream in every cell, so methods are compared on paired noise
    return int(seed) * 100_003 + int(context_index)


def merge_artifacts(previous: dict, current: dict) -> dict:
    """The artifacts of a run made in parts: per task, the current part's summary, with the models and contexts of
    the earlier parts kept beside its own when both parts used the same task file and dataset (`--only
    method=dprior`, then `--only method=cvae` into one folder once kept only the CVAE). A task whose task file or
    dataset changed between parts takes the current part's summary only (the earlier models belong to other data)."""
    out = dict(previous)
    for task, now in current.items():
        before = previous.get(task)
        same = before is not None and all(before.get(k) == now.get(k) for k in ("task_hash", "dataset_hash"))
        if not same:
            out[task] = now
            continue
        out[task] = {
            **now,
            **{k: {**before.get(k, {}), **now.get(k, {})} for k in ("models", "model_sources", "contexts")},
        }
    return out


class Runner:
    def __init__(
        self,
        spec: Spec,
        only: dict[str, list] | None = None,
        executor: str = "local",
        workers: int = 1,
        address: str | None = None,
        run_dir: Path | None = None,
        fresh: bool = False,
        device: str | None = None,
        progress: bool = True,
        mlflow: bool = False,
        record: bool = True,
        recorder: Callable[[Path, str, dict, dict], None] | None = None,
    ):
        """``recorder(run_dir, task_file, row, history)`` streams a recorded (cell, context) as soon as it is planned
        (the CLI passes the Rerun recorder of ``mpd.viz``, a higher layer); without one, the histories are only
        saved, and ``mpd report`` builds the recordings from them."""
        if executor not in ("local", "ray"):
            raise ValueError(f"unknown executor {executor!r} (local, ray)")
        self.spec = spec
        self.cells = spec.cells(only)
        self.executor = executor
        self.workers = max(1, int(workers))
        self.address = address
        self.run_dir = Path(run_dir) if run_dir else runs_dir() / run_id(spec)
        self.fresh = fresh
        self.progress = progress
        self.mlflow = mlflow
        self.record = record
        self.recorder = recorder
        self.unit_nodes: dict[str, int] = {}  # Ray node -> planning units it ran (executor "ray")
        from mpd.device import default_device

        dev = device or (spec.data.device if spec.data.device != "auto" else None)
        self.device = str(dev or default_device())

    # ------------------------------------------------------------------------------------------------ planning
    def n_contexts(self, task: str) -> int:
        ts = self.spec.data.tasks[task]
        return ts.n_contexts or self.spec.data.n_contexts

    def plan(self) -> Plan:
        store = RowStore(self.run_dir) if self.run_dir.exists() and not self.fresh else None
        total = todo = 0
        for cell in self.cells:
            n = self.n_contexts(cell.p["task"])
            total += n
            todo += n - (len(store.done(cell.key)) if store else 0)
        needs = artifacts.needs(self.spec, self.cells)
        return Plan(self.cells, needs, total, todo)

    def describe(self) -> str:
        """The dry run: cells, what would be generated or trained, and an estimate of the work."""
        p = self.plan()
        lines = [
            f"spec {self.spec.name} ({self.spec.path}), hash {self.spec.hash}",
            f"run folder {self.run_dir}",
            "",
        ]
        lines.append(f"{len(p.cells)} cells:")
        for c in p.cells:
            lines.append(f"  {c.key}  {c.label()}")
        lines.append("")
        lines.append("artifacts:")
        for n in p.needs:
            lines.append(f"  {n.describe()}")
        # datasets are generated one after the other; missing models train side by side, up to --workers at once
        todo = [n for n in p.needs if not n.exists]
        n_models = sum(1 for n in todo if n.kind == "model")
        est = sum(n.estimate_s for n in todo if n.kind != "model") + sum(
            n.estimate_s for n in todo if n.kind == "model"
        ) / max(1, min(self.workers, n_models))
        lines.append("")
        build = (
            f"artifacts to build: ~{est / 60:.0f} min of the estimate (rough, 2-core CPU)"
            if todo
            else "nothing to build"
        )
        lines.append(f"units (cell x context): {p.units_total} in all, {p.units_todo} to compute; {build}")
        return "\n".join(lines)

    # ------------------------------------------------------------------------------------------------ running
    def run(self, on_result: Callable[[UnitResult], None] | None = None) -> Path:
        if self.fresh and self.run_dir.exists():
            import shutil

            shutil.rmtree(self.run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        store = RowStore(self.run_dir)
        manifest = self._manifest(status="resolving")
        if self.executor == "ray":
            from mpd import distributed

            distributed.init(self.address, self.workers)
        resolved = artifacts.resolve(
            self.spec, self.cells, progress=self.progress, workers=self.workers, executor=self.executor,
            address=self.address,
        )  # fmt: skip
        # a run made in parts (`--only` one task, then another, into one run folder) keeps every part's artifacts
        manifest["artifacts"] = merge_artifacts(
            self._previous.get("artifacts", {}), {k: v.summary() for k, v in resolved.items()}
        )
        manifest["status"] = "running"
        write_json(manifest, self.run_dir / "manifest.json")
        units = list(self._units(resolved, store))
        log.info("%d units to compute", len(units))
        status = "failed"
        try:
            self._execute(units, store, on_result)
            status = "completed"
        except KeyboardInterrupt:
            status = "interrupted"
            raise
        finally:
            df = store.table()
            if len(df):
                write_parquet(df, self.run_dir / "results.parquet")
            manifest.update(status=status, finished_at=time.time(), n_rows=int(len(df)))
            if self.executor == "ray":
                manifest["ray_nodes"] = self._ray_nodes(resolved)
            write_json(manifest, self.run_dir / "manifest.json")
        if self.mlflow:
            from mpd.experiments.tracking import log_model_to_mlflow, log_run_to_mlflow

            for art in resolved.values():
                for m in art.models.values():
                    log_model_to_mlflow(m.path.parent / "meta.json")
            log_run_to_mlflow(self.run_dir)
        return self.run_dir

    def _manifest(self, status: str) -> dict:
        prev = {}
        if (self.run_dir / "manifest.json").exists():
            import json

            prev = json.loads((self.run_dir / "manifest.json").read_text())
        # the parts of one spec merge (the tasks, cells and artifacts of earlier `--only` parts stay named); a run
        # folder reused for another spec does not inherit them
        self._previous = prev if prev.get("spec_hash") == self.spec.hash else {}
        cells = {c["key"]: c for c in self._previous.get("cells", [])}
        cells.update({c.key: {"key": c.key, **c.p} for c in self.cells})
        return {
            "run_id": self.run_dir.name,
            "spec_name": self.spec.name,
            "spec_hash": self.spec.hash,
            "spec_path": _repo_relative(self.spec.path),
            "spec": self.spec.raw,
            # name -> file and sha256 of every task: reports and recordings find a task given by path by its name
            "task_files": {
                **self._previous.get("task_files", {}),
                **{
                    n: {"path": _repo_relative(self.spec.task_file(n)), "sha256": file_sha256(self.spec.task_file(n))}
                    for n in sorted({c.p["task"] for c in self.cells})
                },
            },
            "cells": sorted(cells.values(), key=lambda c: c["key"]),
            "executor": self.executor,
            "workers": self.workers,
            "device": self.device,
            "cpu": cpu_model(),
            "provenance": provenance(),
            "started_at": prev.get("started_at", time.time()),
            "resumed_at": time.time() if prev else None,
            "status": status,
        }

    def _units(self, resolved: dict, store: RowStore) -> Iterable[Unit]:
        prov_base = provenance()
        base = {
            "run_id": self.run_dir.name,
            "spec_name": self.spec.name,
            "spec_hash": self.spec.hash,
            "git_commit": prov_base["git_commit"],
            "git_dirty": prov_base["git_dirty"],
            "mpd_version": prov_base["mpd_version"],
            "torch_version": prov_base["libraries"].get("torch"),
            "libraries": ",".join(f"{k}={v}" for k, v in prov_base["libraries"].items()),
        }
        record_n = self.spec.data.record_contexts
        for cell in self.cells:
            p = cell.p
            task_art = resolved[p["task"]]
            contexts = task_art.contexts_for(p)
            done = store.done(cell.key)
            model = task_art.model_for(p["method"], p["parametrization"] or "bspline", cell.training_overrides())
            prov = dict(
                base,
                task_hash=task_art.task_hash,
                dataset_id=task_art.dataset_id,
                dataset_hash=task_art.dataset_hash,
                model_id=model.identity if model else "",
                model_hash=model.sha256 if model else "",
                model_steps=model.steps if model else 0,
                model_train_s=model.wall_time_s if model else 0.0,
                contexts_hash=contexts.hash,
                contexts_source=contexts.meta.get("source", ""),
                context_seed=contexts.meta.get("context_seed", -1),
            )
            data_range = task_art.data_range if model is None else None
            for j in range(len(contexts)):
                i = int(contexts.index[j])
                if i in done:
                    continue
                yield Unit(
                    cell.key,
                    p,
                    cell.planner_overrides(),
                    i,
                    contexts.row(j),
                    plan_seed(p["seed"], i),
                    str(model.path) if model else None,
                    self.device,
                    record=j < record_n,
                    provenance=dict(prov, dataset_context_id=int(contexts.context_id[j])),
                    data_range=data_range,
                    task_path=str(self.spec.task_file(p["task"])),
                    fast=self.spec.data.fast and fast_enabled(),
                )

    def _execute(self, units: list[Unit], store: RowStore, on_result) -> None:
        bar = tqdm(
            total=len(units),
            desc=f"{self.spec.name}",
            unit="plan",
            disable=not self.progress,
            dynamic_ncols=True,
        )

        def done(res: UnitResult) -> None:
            store.append(res.cell_key, res.row)
            if res.history is not None:
                save_history(self.run_dir, res)
                self._record(res)
            if on_result is not None:
                on_result(res)
            bar.set_postfix_str(
                f"{res.row['task'][:12]}/{res.row['method']} ok={res.row['success']:.0f}", refresh=False
            )
            bar.update()

        try:
            if self.executor == "ray":
                self._execute_ray(units, done)
            else:
                # serial: this process's threads as they are (`mpd run --threads`); a pool: one thread per worker
                serial = self.workers == 1
                mode, threads = ("serial", None) if serial else ("process", 1)
                for _, res in imap(run_unit, [(u,) for u in units], mode, self.workers, threads, name=_unit_name):
                    done(res)
        finally:
            bar.close()

    def _record(self, res: UnitResult) -> None:
        """Stream a recorded (cell, context) through the recorder, if any, as soon as it is planned."""
        if not self.record or self.recorder is None:
            return
        try:
            self.recorder(self.run_dir, str(self.spec.task_file(res.row["task"])), res.row, res.history)
        except Exception as e:  # a recording must never cost the run its results
            log.warning("recording of %s context %s failed: %s", res.cell_key, res.row["context_index"], e)

    def _execute_ray(self, units: list[Unit], done) -> None:
        import ray

        from mpd import distributed

        distributed.init(self.address, self.workers)
        # each model once in the object store: a worker whose cache lacks it (no shared cache) takes it from there
        blobs = {}
        for u in units:
            if u.model_path and u.model_path not in blobs:
                data = Path(u.model_path).read_bytes()
                blobs[u.model_path] = (u.provenance.get("model_hash", ""), [ray.put(data)])
        items = [(u, blobs.get(u.model_path)) for u in units]
        for _, (res, node) in imap(_ray_unit, items, "ray", self.workers, address=self.address, name=_unit_name):
            self.unit_nodes[node] = self.unit_nodes.get(node, 0) + 1
            done(res)

    def _ray_nodes(self, resolved: dict) -> dict:
        """Which Ray node did what: dataset chunks (from the chunks' records), trainings (the models' metas) and
        planning units of this run."""
        from mpd.data.storage import read_sidecar

        chunks, trainings = {}, {}
        for task_name, art in resolved.items():
            rd = self.spec.definition(task_name)
            for i in range(rd.definition.n_chunks):
                node = (read_sidecar(rd.data_dir, i) or {}).get("node")
                if node:
                    chunks[node] = chunks.get(node, 0) + 1
            for m in art.models.values():
                node = json.loads((m.path.parent / "meta.json").read_text()).get("node")
                if node:
                    trainings[node] = trainings.get(node, 0) + 1
        return {"dataset_chunks": chunks, "trainings": trainings, "units": dict(self.unit_nodes)}


def _unit_name(item: tuple) -> str:
    unit = item[0]
    return f"cell {unit.cell_key} context {unit.context_index}"


_VERIFIED_MODELS: dict[str, str] = {}  # driver's model path -> the path of the same file on this worker


def _ray_unit(unit: Unit, blob: tuple[str, list] | None = None) -> tuple[UnitResult, str]:
    """Ray task: one unit; returns its result and the node it ran on. A model missing from this worker's view of the
    cache (the cache is not shared) is written into this worker's cache from the object store, checked by sha256."""
    from mpd import distributed

    if unit.model_path and blob is not None:
        unit.model_path = _model_here(unit.model_path, *blob)
    return run_unit(unit), distributed.node_id()


def _model_here(path: str, sha256: str, ref: list) -> str:
    if path in _VERIFIED_MODELS:
        return _VERIFIED_MODELS[path]
    import ray

    from mpd import distributed
    from mpd.paths import cache_dir

    here = Path(path)
    if not (here.is_file() and file_sha256(here) == sha256):
        rel = Path(*here.parts[-4:])  # models/<task>/<kind-par-identity>/model.pt
        here = cache_dir() / rel
        if not (here.is_file() and file_sha256(here) == sha256):
            data = distributed.checked(ray.get(ref[0]), sha256, f"model {path}")
            here.parent.mkdir(parents=True, exist_ok=True)
            tmp = here.with_name(f".{here.name}.ray-{os.getpid()}")
            tmp.write_bytes(data)
            os.replace(tmp, here)
    _VERIFIED_MODELS[path] = str(here)
    return str(here)


def save_history(run_dir: Path, res: UnitResult) -> Path:
    """The recorded batch of one (cell, context): dense trajectories at every step, for recordings and figures."""
    d = Path(run_dir) / "histories"
    d.mkdir(exist_ok=True)
    path = d / f"{res.cell_key}-ctx{res.row['context_index']}.npz"
    tmp = path.with_suffix(".tmp.npz")
    meta = {k: v for k, v in res.row.items() if not k.startswith(("time_", "info_"))}
    np.savez_compressed(tmp, **res.history, row_json=np.array(json.dumps(meta, default=str)))
    os.replace(tmp, path)
    return path


def latest_run(name: str | None = None) -> Path:
    """The most recently modified run folder (of a spec, when given)."""
    runs = [p for p in runs_dir().iterdir() if (p / "manifest.json").exists()]
    if name:
        runs = [p for p in runs if p.name == name or p.name.startswith(f"{name}-")]
    if not runs:
        raise FileNotFoundError(f"no run found{' for ' + name if name else ''} in {runs_dir()}")
    return max(runs, key=lambda p: (p / "manifest.json").stat().st_mtime)


def resolve_run(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.is_dir() and (p / "manifest.json").exists():
        return p
    if name_or_path == "latest":
        return latest_run()
    cand = runs_dir() / name_or_path
    if cand.is_dir():
        return cand
    return latest_run(name_or_path)


__all__ = ["Plan", "Runner", "latest_run", "plan_seed", "read_results", "resolve_run", "run_id"]


def _repo_relative(path) -> str:
    """A spec inside the repository is recorded relative to its root, so manifests and reports do not depend on
    where the clone lives."""
    from mpd.paths import REPO_ROOT

    p = Path(path).resolve()
    try:
        return str(p.relative_to(Path(REPO_ROOT).resolve()))
    except ValueError:
        return str(p)
