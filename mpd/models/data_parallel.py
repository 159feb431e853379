"""One diffusion training over several processes of one machine: each rank computes the loss of a slice of every
batch, the ranks average their gradients, and every rank takes the same optimizer step.

Why: a training step of the priors' networks runs on two threads hardly faster than on one (each convolution split
too finely), while two processes each on half the batch, each on its own core, finish a step sooner. So on a
machine whose cores would otherwise idle, ``mpd train --data-parallel N`` trains one model faster in wall-clock
time; it spends more CPU-hours a step than one process does (a half batch is less than half the work of a whole
one only in FLOPs), so trainings side by side, one core each, remain the better use of a busy machine. Measured:
``benchmarks/test_bench_data_parallel.py``, docs/PERFORMANCE.md.

What it computes: the batch, the diffusion steps and the noise are drawn by every rank from the same generator, in
the one-process order, for the whole batch; rank ``r`` keeps rows ``[r*b/N, (r+1)*b/N)``. The diffusion loss is a
mean over samples, so the average of the N slices' gradients is the whole batch's gradient, and the clipping,
AdamW and EMA that follow are the one-process step's, on every rank. Only the float rounding of the sums differs:
the same model identity, another execution mode (recorded in the checkpoint's ``execution``, e.g. ``compiled/2``),
and a training may switch between one process and several at any checkpoint. Runs repeat bit for bit for the same
rank count on the same CPU type and thread count: every rank adds the ranks' gradients in rank order, so every
rank holds the same bits.

How: rank 0 is the calling process (progress bar, validation, checkpoints, the final model); ranks 1..N-1 are
spawned processes that start from rank 0's training state and end with the loop. The gradients meet in shared
memory: each rank writes its own into its row of a ``(ranks, n)`` buffer, waits at a barrier, and sums the rows
(two buffers, used in turn, so that no rank writes a buffer another is still reading). A Ctrl-C (SIGINT) to any
rank stops every rank after the same whole step, and rank 0 saves ``last.pt``; a rank that dies breaks the barrier,
and the others fail with an error instead of waiting.
"""

from __future__ import annotations

import contextlib
import io
import threading
from collections.abc import Iterator
from typing import Any

import torch

TIMEOUT_S = 1800.0  # a rank waiting this long at a barrier fails (the first step compiles: up to ~10 min)


def label(mode: str, ranks: int) -> str:
    """The execution record's name of ``mode`` run on ``ranks`` ranks (``mode`` itself for one)."""
    return mode if ranks == 1 else f"{mode}/{ranks}"


def check(kind: str, device: torch.device, batch_size: int, ranks: int) -> None:
    """Raise ValueError, naming the setting, unless a training of this kind can run on ``ranks`` ranks."""
    if ranks < 1:
        raise ValueError(f"data_parallel = {ranks}: the number of ranks is at least 1")
    if ranks == 1:
        return
    if kind != "diffusion":
        raise ValueError(f"data_parallel = {ranks}: only a diffusion training runs on several ranks, not {kind}")
    if torch.device(device).type != "cpu":
        raise ValueError(f"data_parallel = {ranks}: the ranks share a CPU's cores; device {device} trains on one")
    if batch_size % ranks:
        raise ValueError(f"data_parallel = {ranks}: the batch size {batch_size} is not a multiple of the ranks")


class Link:
    """What the ranks share: two gradient buffers ``(ranks, n + 1)`` (the gradients and the loss), two flag rows
    and a barrier. Made by rank 0, handed to the other ranks when they are spawned; ``rank`` is set in each."""

    def __init__(self, ranks: int, n: int, barrier: Any):
        self.rank, self.ranks, self.barrier = 0, ranks, barrier
        self.bufs = [torch.zeros(ranks, n + 1).share_memory_() for _ in range(2)]
        self.flags = [torch.zeros(ranks).share_memory_() for _ in range(2)]
        self.turn = self.flag_turn = 0

    def wait(self) -> None:
        try:
            self.barrier.wait(timeout=TIMEOUT_S)
        except threading.BrokenBarrierError:
            raise RuntimeError(
                f"data-parallel training, rank {self.rank}: another rank stopped (it failed, or timed out after "
                f"{TIMEOUT_S:.0f} s); see its error above"
            ) from None

    def mean(self, row: Any) -> torch.Tensor:
        """The ranks' mean of ``row`` (this rank's values, written by ``row(out)`` into a buffer row), added in rank
        order on every rank."""
        buf = self.bufs[self.turn]
        self.turn ^= 1
        row(buf[self.rank])
        self.wait()
        total = buf[0].clone()
        for r in range(1, self.ranks):
            total.add_(buf[r])
        return total.div_(self.ranks)

    def any(self, flag: bool) -> bool:
        """Whether ``flag`` holds on any rank (every rank calls it at the same point)."""
        flags = self.flags[self.flag_turn]
        self.flag_turn ^= 1
        flags[self.rank] = 1.0 if flag else 0.0
        self.wait()
        return bool(flags.max() > 0)

    def abort(self) -> None:
        """Break the barrier: every rank waiting at it, or arriving later, fails."""
        self.barrier.abort()


class Shard:
    """A rank's rows of every batch and the averaging of the ranks' gradients (and losses)."""

    def __init__(self, link: Link, batch_size: int, params: list[torch.nn.Parameter]):
        self.link = link
        per = batch_size // link.ranks
        self.rows = slice(link.rank * per, (link.rank + 1) * per)
        self.params = params
        self.sizes = [p.numel() for p in params]

    def take(self, *tensors: Any) -> list[Any]:
        """This rank's rows of each tensor (or of each tensor of a dict)."""
        r = self.rows
        return [{k: v[r] for k, v in t.items()} if isinstance(t, dict) else t[r] for t in tensors]

    @torch.no_grad()
    def average(self, loss: torch.Tensor) -> torch.Tensor:
        """Replace every gradient by its mean over the ranks; return the ranks' mean ``loss`` (detached)."""
        for p in self.params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        grads = [p.grad for p in self.params]

        def write(out: torch.Tensor) -> None:
            torch._foreach_copy_(list(out[:-1].split(self.sizes)), [g.reshape(-1) for g in grads])
            out[-1] = loss.detach().float()

        total = self.link.mean(write)
        torch._foreach_copy_(grads, [v.view_as(g) for v, g in zip(total[:-1].split(self.sizes), grads)])
        return total[-1]


def state_bytes(state: dict[str, Any]) -> bytes:
    """A training state (:meth:`mpd.models.train.TrainingState.checkpoint`) as bytes, for the spawned ranks."""
    buf = io.BytesIO()
    torch.save(state, buf)
    return buf.getvalue()


def read_state(data: bytes) -> dict[str, Any]:
    return torch.load(io.BytesIO(data), map_location="cpu", weights_only=False)


def _follower(link: Link, rank: int, threads: int, payload: dict[str, Any]) -> None:
    torch.set_num_threads(threads)
    link.rank = rank
    from mpd.models.train import follow

    try:
        with contextlib.suppress(KeyboardInterrupt):
            follow(link, **payload)
    except BaseException:
        link.abort()
        raise


@contextlib.contextmanager
def group(ranks: int, n_params: int, payload: dict[str, Any]) -> Iterator[Link]:
    """Spawn ranks 1..``ranks``-1, each calling :func:`mpd.models.train.follow` with ``payload``, and yield rank 0's
    :class:`Link` (the calling process) for the ``with`` block; then wait for them to end."""
    ctx = torch.multiprocessing.get_context("spawn")
    link = Link(ranks, n_params, ctx.Barrier(ranks))
    procs = [
        ctx.Process(target=_follower, args=(link, r, torch.get_num_threads(), payload), name=f"mpd-rank-{r}")
        for r in range(1, ranks)
    ]
    for p in procs:
        p.start()
    ok = False
    try:
        yield link
        ok = True
    except BaseException:
        link.abort()
        raise
    finally:
        for p in procs:
            p.join(timeout=60 if ok else 10)
            if p.is_alive():
                p.terminate()
                p.join()
    failed = [r for r, p in enumerate(procs, 1) if p.exitcode != 0]
    if failed:
        raise RuntimeError(f"data-parallel training: rank(s) {failed} exited with an error (see stderr)")


__all__ = ["Link", "Shard", "check", "group", "label", "read_state", "state_bytes"]
