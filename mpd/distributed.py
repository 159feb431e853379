"""Ray, as every stage uses it: dataset chunks, trainings and planning units run as Ray tasks (one CPU each, or one
GPU for a training when the cluster has GPUs), retried by Ray when a worker dies.

Artifacts cross nodes through Ray's object store: a task returns the bytes it wrote (a dataset chunk, a model) with
their sha256, and the driver writes them into its own cache after checking the hash on arrival, unless its cache
already holds that very file (a shared ``$MPD_CACHE``). So the cache may be shared between the nodes or not; a
worker's files are never trusted by hash alone on the driver's side, nor the other way round.
"""

from __future__ import annotations

import hashlib
import logging


def init(address: str | None = None, num_cpus: int | None = None) -> None:
    """Connect to the cluster at ``address``, or start a local Ray with ``num_cpus`` (once per process). Every worker
    of this job pins its threads when it starts (`mpd.executor.pin_threads`: one thread, as its task has one CPU)."""
    import ray

    if ray.is_initialized():
        return
    kw = {"address": address} if address else {"num_cpus": num_cpus}
    hook = {"worker_process_setup_hook": "mpd.executor.pin_threads"}
    ray.init(include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False, runtime_env=hook, **kw)


def node_id() -> str:
    """The Ray node this code runs on ("" outside a Ray worker)."""
    try:
        import ray

        return ray.get_runtime_context().get_node_id() if ray.is_initialized() else ""
    except Exception:
        return ""


def cluster_gpus() -> float:
    import ray

    return float(ray.cluster_resources().get("GPU", 0.0))


def cluster_cpus() -> int:
    import ray

    return int(ray.cluster_resources().get("CPU", 1))


def checked(data: bytes, sha256: str, what: str) -> bytes:
    """``data`` when its sha256 is ``sha256``; else a RuntimeError naming ``what`` (corrupted in transit)."""
    got = hashlib.sha256(data).hexdigest()
    if got != sha256:
        raise RuntimeError(f"{what}: received bytes have sha256 {got[:16]}…, the worker declared {sha256[:16]}…")
    return data


__all__ = ["checked", "cluster_cpus", "cluster_gpus", "init", "node_id"]
