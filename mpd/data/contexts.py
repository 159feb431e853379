"""Start/goal contexts: sampling for datasets, and the fixed evaluation contexts of each task.

Every context is drawn from its own random stream (a seed derived from the dataset seed and the context
index), so a context does not depend on how the work is split into chunks or workers.

Sampling (the authors' generator): start and goal uniform within the joint limits, rejected until valid with
the task's clearance; EnvWarehouse draws end-effector poses from the task file's ``pose_regions`` and solves
IK ("Paper vs code" 14): with probability ``region_pair_probability`` the start and the goal come from two
different regions, otherwise only the goal does and the start is a random valid configuration. The goal pose
of an end-effector-goal context is FK(q_goal), the pose the path really ends at.
"""

from __future__ import annotations

import os
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mpd.data.checkers import SphereChecker
from mpd.data.definition import task_data_hash
from mpd.data.planning import JointSpacePlanner, PlannerSettings, default_check_step, problem_seed
from mpd.paths import cache_dir
from mpd.robots.exact import mm as exact_mm
from mpd.robots.ik import solve_ik
from mpd.tasks import Task
from mpd.tasks.spec import PoseRegionSpec

CONTEXTS_VERSION = 1  # bump when the evaluation-context algorithm changes (it is part of the cache key)


class ContextError(RuntimeError):
    """No valid context found within the allowed number of tries."""


@dataclass
class SampledContext:
    q_start: np.ndarray
    q_goal: np.ndarray
    source: int  # 0 uniform, 1 goal from a pose region, 2 start and goal from two pose regions


SOURCES = ("uniform", "region_goal", "region_pair", "problem")  # "problem": a benchmark problem's (ProblemSettings)


def sample_region_pose(region: PoseRegionSpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A pose in a region: x, y, z each uniform in one of its intervals; R = R_base R_euler('xyz', deg)."""
    from scipy.spatial.transform import Rotation

    def pick(intervals) -> float:
        lo, hi = intervals[int(rng.integers(len(intervals)))]
        return float(rng.uniform(lo, hi))

    pos = np.array([pick(region.x), pick(region.y), pick(region.z)])
    ang = [pick(region.rot_x_deg), pick(region.rot_y_deg), pick(region.rot_z_deg)]
    base = torch.as_tensor(np.asarray(region.rotation_base, dtype=np.float64))
    rot = exact_mm(base, torch.as_tensor(Rotation.from_euler("xyz", ang, degrees=True).as_matrix())).numpy()
    return pos, rot


class ContextSampler:
    """Valid (start, goal) pairs of a task for a validity checker (``valid(Q) -> bool mask``).

    Args:
        min_distance: minimum joint-space distance between start and goal.
        max_tries: candidate draws (uniform configurations, or IK restarts) per configuration before giving up
            (the authors use 500).
        batch: candidates checked per call (the stream is consumed in whole batches, so results are
        reproducible).
    """

    def __init__(
        self,
        task: Task,
        checker,
        min_distance: float = 0.0,
        max_tries: int = 500,
        batch: int = 32,
        ik_restarts: int = 128,
        ik_iters: int = 30,
        ik_restarts_per_pose: int = 128,
        max_poses: int = 50,
    ):
        self.task = task
        self.robot = task.robot
        self.checker = checker
        self.min_distance = float(min_distance)
        self.max_tries = int(max_tries)
        self.batch = int(batch)
        self.ik_restarts = int(ik_restarts)
        # All restarts of a pose in one batch: the loop stops at the first valid solution (faster per Warehouse
        # context than 4 batches of 32). 30 iterations: on Warehouse region poses the share of poses solved was the
        # same with 20, 30, 50 and 100 iterations (converged restarts per pose 8.1, 9.2, 10.3, 11.1 of 32), and
        # fewer iterations cost less CPU per context.
        self.ik_iters = int(ik_iters)
        self.ik_restarts_per_pose = int(ik_restarts_per_pose)
        self.max_poses = int(max_poses)
        self.lo = self.robot.q_min.numpy()
        self.hi = self.robot.q_max.numpy()
        ctx = task.spec.context
        self.regions = list(ctx.pose_regions)
        self.pair_probability = float(ctx.region_pair_probability)

    def uniform(self, rng: np.random.Generator, away_from: np.ndarray | None = None) -> np.ndarray:
        """A valid configuration uniform within the limits (at least ``min_distance`` from ``away_from``)."""
        for _ in range(-(-self.max_tries // self.batch)):
            q = rng.uniform(self.lo, self.hi, (self.batch, self.robot.dof))
            ok = self.checker.valid(q)
            if away_from is not None and self.min_distance > 0:
                ok &= np.linalg.norm(q - away_from, axis=1) >= self.min_distance
            if ok.any():
                return q[int(np.argmax(ok))]
        raise ContextError(f"{self.task.name}: no valid configuration in {self.max_tries} uniform draws")

    def from_region(
        self, region: PoseRegionSpec, rng: np.random.Generator, away_from: np.ndarray | None = None
    ) -> np.ndarray:
        """A valid configuration whose end effector reaches a random pose of the region (see :meth:`_region`)."""
        out = _drive([self._region(region, rng, away_from)], self)[0]
        if isinstance(out, ContextError):
            raise out
        return out

    def _region(self, region: PoseRegionSpec, rng: np.random.Generator, away_from: np.ndarray | None):
        """The steps of :meth:`from_region` as a coroutine: it yields IK problems (:class:`_IKProblem`) and is sent
        the solution (or None), so that :func:`_drive` can solve the problems of many contexts in one batch.

        Like the authors' generator, a pose is retried with fresh random IK restarts until a valid solution
        turns up (up to ``ik_restarts_per_pose``), so that poses that are hard to reach without collision keep
        their weight; a pose without one is replaced by a new pose, up to ``max_poses`` poses.
        """
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        calls = -(-self.ik_restarts_per_pose // self.ik_restarts)
        for _ in range(self.max_poses):
            pos, rot = sample_region_pose(region, rng)
            for _ in range(calls):
                q0 = self.robot.random_q(self.ik_restarts, gen, dtype=torch.float64)
                q = yield _IKProblem(pos, rot, q0, away_from)
                if q is not None:
                    return q
        raise ContextError(f"{self.task.name}: no valid IK solution in region {region.name!r}")

    def _steps(self, rng: np.random.Generator):
        """The steps of :meth:`sample` as a coroutine (see :meth:`_region`)."""
        if not self.regions:
            q_start = self.uniform(rng)
            return SampledContext(q_start, self.uniform(rng, away_from=q_start), 0)
        if len(self.regions) > 1 and rng.random() < self.pair_probability:
            i, j = rng.choice(len(self.regions), size=2, replace=False)
            q_start = yield from self._region(self.regions[int(i)], rng, None)
            q_goal = yield from self._region(self.regions[int(j)], rng, q_start)
            return SampledContext(q_start, q_goal, 2)
        k = int(rng.integers(len(self.regions)))
        q_start = self.uniform(rng)
        return SampledContext(q_start, (yield from self._region(self.regions[k], rng, q_start)), 1)

    def sample(self, rng: np.random.Generator) -> SampledContext:
        out = _drive([self._steps(rng)], self)[0]
        if isinstance(out, ContextError):
            raise out
        return out

    def sample_many(self, rngs: list[np.random.Generator]) -> list[SampledContext | ContextError]:
        """:meth:`sample` for many contexts, each from its own stream, with their IK problems solved together:
        the same contexts as one :meth:`sample` call per stream, in a fraction of the time (the iterations of
        128 restarts of one pose are dominated by per-call overhead). A context without a valid candidate comes
        back as its :class:`ContextError`."""
        return _drive([self._steps(r) for r in rngs], self)


@dataclass
class _IKProblem:
    pos: np.ndarray  # (3,)
    rot: np.ndarray  # (3, 3)
    q0: torch.Tensor  # (R, dof) the restarts' initial configurations
    away_from: np.ndarray | None  # a configuration the solution must keep min_distance from


def _drive(steps: list, sampler: ContextSampler) -> list:
    """Run coroutines (:meth:`ContextSampler._steps`) to their ends, solving the IK problems they are waiting on
    in one :func:`solve_ik` batch per round; each coroutine's result, its ContextError if it raised one."""
    out: list = [None] * len(steps)
    waiting: dict[int, _IKProblem] = {}

    def advance(k: int, value) -> None:
        try:
            waiting[k] = steps[k].send(value)
        except StopIteration as stop:
            waiting.pop(k, None)
            out[k] = stop.value
        except ContextError as err:
            waiting.pop(k, None)
            out[k] = err

    for k in range(len(steps)):
        advance(k, None)
    md = sampler.min_distance
    while waiting:
        ks = list(waiting)
        probs = [waiting[k] for k in ks]
        away = np.array([p.away_from if p.away_from is not None else np.full(sampler.robot.dof, np.nan) for p in probs])
        has_away = ~np.isnan(away[:, 0]) & (md > 0)

        def valid(q: torch.Tensor, target: torch.Tensor, away=away, has_away=has_away) -> np.ndarray:
            qn, t = q.numpy(), target.numpy()
            ok = sampler.checker.valid(qn)
            far = np.linalg.norm(qn - away[t], axis=1) >= md
            return ok & np.where(has_away[t], far, True)

        res = solve_ik(
            sampler.robot,
            torch.as_tensor(np.stack([p.pos for p in probs])),
            torch.as_tensor(np.stack([p.rot for p in probs])),
            n_restarts=sampler.ik_restarts,
            q_restarts=torch.stack([p.q0 for p in probs]),
            valid_target=valid,
            max_iters=sampler.ik_iters,
        )
        for i, k in enumerate(ks):
            advance(k, res.q[i].numpy() if bool(res.success[i]) else None)
    return out


# ----------------------------------------------------------------------------------------------------
@dataclass
class Contexts:
    """Fixed contexts of a task; ``ee_pos``/``ee_rot`` (FK of ``q_goal``) only for end-effector-goal tasks."""

    task: str
    q_start: np.ndarray  # (n, dof)
    q_goal: np.ndarray  # (n, dof)
    ee_pos: np.ndarray | None = None  # (n, 3)
    ee_rot: np.ndarray | None = None  # (n, 3, 3)
    source: np.ndarray | None = None  # (n,) index into SOURCES

    def __len__(self) -> int:
        return len(self.q_start)


def ee_goal_pose(task: Task, q_goal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p, r = task.robot.ee_pose(torch.as_tensor(q_goal, dtype=torch.float64), exact=True)  # the same bits on every CPU
    return p.numpy(), r.numpy()


def evaluation_seed(task: Task) -> int:
    return problem_seed("evaluation-contexts", task.name)


def contexts_cache_path(task: Task, n: int) -> Path:
    return cache_dir() / "contexts" / f"{task.name}-{task_data_hash(task)[:16]}-n{n}-v{CONTEXTS_VERSION}.npz"


def _cached_sets(task: Task) -> dict[int, Path]:
    out = {}
    pattern = f"{task.name}-{task_data_hash(task)[:16]}-n*-v{CONTEXTS_VERSION}.npz"
    for p in contexts_cache_path(task, 0).parent.glob(pattern):
        try:
            out[int(p.name.rsplit("-n", 1)[1].split("-v")[0])] = p
        except ValueError:
            continue
    return out


def evaluation_contexts(task: Task, n: int = 100, refresh: bool = False) -> Contexts:
    """The fixed evaluation contexts of a task: the same for every method and run.

    Context i comes from a stream seeded by (task name, i), independent of any dataset. It is valid with the
    task's clearance in the scene with the extra objects (which contains the training obstacles, so it is
    valid in both), its start and goal are at least ``context.min_start_goal_distance`` apart, and RRTConnect
    finds a path between them in the training scene. Cached under ``cache_dir()/contexts/``, keyed by the task
    file's hash.
    """
    path = contexts_cache_path(task, n)
    if not refresh:
        # context i depends only on (task, i): the first n of a larger cached set are the same contexts
        for m, p in sorted(_cached_sets(task).items()):
            if m >= n:
                try:
                    with np.load(p) as z:
                        return _from_arrays(task, {k: v[:n] for k, v in z.items()})
                except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:  # a damaged cache file
                    warnings.warn(f"{p}: does not read back ({type(e).__name__}); made again", stacklevel=2)
                    p.unlink(missing_ok=True)
    cl = task.spec.collision.clearance
    both = SphereChecker(task, extra_objects=True, clearance=cl)
    train = SphereChecker(task, extra_objects=False, clearance=cl)
    sampler = ContextSampler(task, both, min_distance=task.spec.context.min_start_goal_distance, max_tries=5000)
    settings = PlannerSettings(
        time_limit=task.spec.data.planner_time_limit, simplify="none", check_step=default_check_step(task)
    )
    planner = JointSpacePlanner(train, settings, task.spec.trajectory.n_points)
    seed = evaluation_seed(task)
    qs, qg, src = [], [], []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        for attempt in range(100):
            try:
                c = sampler.sample(rng)
            except ContextError:
                continue
            if planner.plan(c.q_start, c.q_goal, problem_seed(seed, i, attempt)).success:
                break
        else:
            raise ContextError(f"{task.name}: evaluation context {i} has no solvable candidate in 100 attempts")
        qs.append(c.q_start)
        qg.append(c.q_goal)
        src.append(c.source)
    arrays = {"q_start": np.array(qs), "q_goal": np.array(qg), "source": np.array(src, dtype=np.int8)}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    return _from_arrays(task, arrays)


def _from_arrays(task: Task, a: dict) -> Contexts:
    ee_pos = ee_rot = None
    if task.ee_goal:
        ee_pos, ee_rot = ee_goal_pose(task, a["q_goal"])
    return Contexts(task.name, a["q_start"], a["q_goal"], ee_pos, ee_rot, a.get("source"))
