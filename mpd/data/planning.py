"""Joint-space paths with OMPL: RRTConnect, path simplification, resampling to exactly ``n_points`` states.

Reproducibility. OMPL draws every random number from generators seeded by one global seed generator
(``ompl.util.RNG.setSeed``). Each problem reseeds it with a seed derived from (dataset seed, context index)
and then builds its own space, planner and simplifier, so a path depends on neither the worker nor the
problems solved before it. RRTConnect stops at its first solution, so a problem solved within the time limit
is reproducible; only a problem that runs into the limit could end differently on a slower machine (or on a
busy one). ``max_checks`` replaces that limit by a budget of collision checks (states and edges checked) per
problem, which ends the same way on every machine; the time limit then stays only as a safety net. The
authors simplify with ``simplify(path, maxTime=0.1)``, whose result depends on how much work fits into 0.1 s;
``simplifyMax`` runs the same steps to completion and is deterministic.

Collision checking of edges. With the sphere model an edge is checked by the compiled checker in one call: its
end state, a coarse pass spread over the edge (which stops most edges in collision after a few states), then the
rest; with PyBullet, state by state through OMPL's own discrete motion validator. Both check the states
``ceil(|b - a| / check_step)`` equal steps apart.

Resampling. Like OMPL's ``PathGeometric.interpolate(n)`` the simplified path keeps its vertices and gets extra
states on each edge in proportion to its length; OMPL's version only adds states, ours hits ``n_points``
exactly. The states are taken from the grid each edge was checked at (see :func:`resample_path`), so that the
stored path, checked again at ``check_step``, visits checked states only; the re-check is done and a path that
fails it (possible for short paths, which need states between grid points) is reported, not stored.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from mpd.data.checkers import MeshChecker, SphereChecker, grid_count, path_valid


@dataclass(frozen=True)
class PlannerSettings:
    """OMPL settings of a dataset (``[planner]`` of a dataset definition)."""

    name: Literal["RRTConnect"] = "RRTConnect"
    time_limit: float = 10.0  # seconds per problem (the authors' value)
    range: float = 0.0  # RRTConnect step; 0 = OMPL's default (0.2 x the space's maximum extent)
    check_step: float = 0.01  # joint-space distance between checked states along an edge
    simplify: Literal["max", "none"] = "max"
    # how the n_points states are shared among the simplified path's edges (see resample_path): "arc_length", in
    # proportion to each edge's length like OMPL's interpolate(n); "v1", the allocation of mpd until 2026-12-02
    # (a bug: about equally many states per edge, capped by its grid), kept for the definitions generated with it
    resample: Literal["arc_length", "v1"] = "arc_length"
    # a budget of collision checks per problem (state checks + edge checks), 0 = none. With a budget a problem
    # that is not solved within it fails with status "budget" after the same work on every machine; without one,
    # the time limit decides, and a problem near it can end differently on a slower or busier machine
    max_checks: int = 0

    def validate(self) -> None:
        if self.time_limit <= 0:
            raise ValueError("time_limit must be positive")
        if self.check_step <= 0:
            raise ValueError("check_step must be positive")
        self.validate_fixed_fields()

    def validate_fixed_fields(self) -> None:
        """The fields that have no task-dependent default (a definition file may leave the others to its task)."""
        if self.max_checks < 0:
            raise ValueError("max_checks must be >= 0 (0 = no budget: the time limit alone)")
        if self.range < 0:
            raise ValueError("range must be >= 0 (0 = OMPL default)")
        if self.resample not in ("arc_length", "v1"):
            raise ValueError(f"resample must be arc_length or v1, got {self.resample!r}")


@dataclass
class PlanResult:
    success: bool
    status: str  # "ok", "invalid_start", "invalid_goal", "timeout", "budget", "post_check"
    time: float  # seconds: planning + simplification + resampling
    path: np.ndarray | None = None  # (n_points, dof)
    n_vertices: int = 0  # after simplification
    stats: dict = field(default_factory=dict)


def default_check_step(task) -> float:
    """Joint-space distance between checked states: 0.01 (m or rad) for the 2-D tasks, 0.02 rad for the Panda,
    whose hand moves about 2 cm or less per 0.02 rad of joint-space distance (the clearance is 2 cm). The
    authors leave OMPL's default, 1 % of the space's extent: 0.028 m (point mass), 0.08-0.10 rad (planar
    arms), 0.13 rad (Panda)."""
    return 0.02 if task.robot.dof >= 7 else 0.01


def problem_seed(*parts: int | str) -> int:
    """A seed in [1, 2^31 - 1] from (dataset seed, index, ...); 0 would make OMPL pick a random seed."""
    h = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return 1 + int.from_bytes(h[:8], "little") % (2**31 - 2)


def _allocate(total: int, weights: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Integers lo <= k <= hi summing to total (sum(lo) <= total <= sum(hi)): lo plus the rest shared in proportion
    to the weights by largest remainder (ties to the lower index); an entry whose share would pass its cap is set
    to the cap and the rest is shared again among the others."""
    k = lo.astype(np.int64).copy()
    weights = np.asarray(weights, dtype=np.float64)
    while True:
        rest = total - int(k.sum())
        free = k < hi
        if rest <= 0 or not free.any():
            return k
        share = rest * np.where(free, weights, 0.0) / weights[free].sum()
        add = np.floor(share).astype(np.int64)
        extra = rest - int(add.sum())
        order = np.argsort(-np.where(free, share - add, -np.inf), kind="stable")[:extra]
        add[order] += 1
        over = k + add > hi
        if not over.any():
            return k + add
        k[over] = hi[over]


def _allocate_v1(total: int, weights: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The allocation of mpd until 2026-12-02, kept so that the datasets generated with it regenerate byte for byte
    (their definitions say ``resample = "v1"``). Meant to be proportional, it adds one to every free entry per
    round, so the states end up about equal per edge (capped by the edge's grid): short edges get many, long ones
    few."""
    k = lo.astype(np.int64).copy()
    while k.sum() < total:
        free = k < hi
        ideal = np.where(free, total * weights / weights[free].sum(), 0.0)
        gap = np.where(free, ideal - k, -np.inf)
        rest = total - int(k.sum())
        order = np.argsort(-gap, kind="stable")[: min(rest, int(free.sum()))]
        k[order] += 1
    return k


def resample_path(vertices: np.ndarray, n: int, step: float, allocation: str = "arc_length") -> np.ndarray:
    """Exactly n states along a polyline, placed on the grid its edges were checked at.

    Each edge a -> b was checked at ``edge_states(a, b, step)``: the points a + (k / m)(b - a), k = 0..m,
    m = ceil(|b - a| / step). When the edges hold at least n - 1 grid intervals in all, the states are chosen
    among these grid points (the vertices included), so that checking the result again at ``step`` visits only
    checked points. Otherwise every grid point is kept and the missing states are spread over the grid
    intervals (those are checked afresh by the caller). With more than n vertices: n states equally spaced in
    arc length. ``allocation``: "arc_length" shares the states among the edges in proportion to their grid counts
    (their lengths); "v1" with :func:`_allocate_v1` (see ``PlannerSettings.resample``).
    """
    allocate = _allocate_v1 if allocation == "v1" else _allocate
    v = np.asarray(vertices, dtype=np.float64)
    if len(v) > 1:
        keep = np.concatenate([[True], np.linalg.norm(np.diff(v, axis=0), axis=1) > 0])
        v = v[keep]
    if len(v) == 1:
        return np.repeat(v, n, axis=0)
    seg = np.linalg.norm(np.diff(v, axis=0), axis=1)
    if len(v) > n:
        s = np.concatenate([[0.0], np.cumsum(seg)])
        t = np.linspace(0.0, s[-1], n)
        return np.stack([np.interp(t, s, v[:, k]) for k in range(v.shape[1])], 1)
    grid = np.array([grid_count(x, step) for x in seg])
    out = [v[:1]]
    if grid.sum() >= n - 1:
        m = allocate(n - 1, grid.astype(np.float64), np.ones_like(grid), grid)
        for i, (g, k) in enumerate(zip(grid, m)):
            idx = np.round(np.arange(1, k + 1) * g / k).astype(np.int64)  # strictly increasing since k <= g
            out.append(v[i] + (idx[:, None] / g) * (v[i + 1] - v[i]))
    else:
        sub = allocate(
            n - 1,
            np.repeat(seg / grid, grid),
            np.ones(grid.sum(), np.int64),
            np.full(grid.sum(), n, np.int64),
        )
        j = 0
        for i, g in enumerate(grid):
            for k in range(g):
                t = (k + np.arange(1, sub[j] + 1) / sub[j]) / g
                out.append(v[i] + t[:, None] * (v[i + 1] - v[i]))
                j += 1
    return np.concatenate(out)


class JointSpacePlanner:
    """RRTConnect in a task's joint space with a validity checker; one :meth:`plan` call per problem."""

    def __init__(
        self,
        checker: SphereChecker | MeshChecker,
        settings: PlannerSettings,
        n_points: int,
        chunk: int = 32,
        store_dtype: type | None = None,
    ):
        from ompl import util as ou

        ou.setLogLevel(ou.LOG_WARN)
        self.checker = checker
        self.settings = settings
        self.n_points = int(n_points)
        self.chunk = int(chunk)
        # paths are checked after rounding to the dtype they are stored in: what is stored is what was checked
        self.store_dtype = store_dtype
        robot = checker.task.robot
        self.dof = robot.dof
        self.lo = robot.q_min.numpy()
        self.hi = robot.q_max.numpy()
        self.batched = isinstance(checker, SphereChecker)
        self.n_checks = 0  # collision checks (states + edges) of the current problem

    def _exhausted(self) -> bool:
        return self.n_checks >= self.settings.max_checks

    # -- OMPL callbacks ----------------------------------------------------------------------------------
    def _state(self, s) -> np.ndarray:
        return np.array([s[i] for i in range(self.dof)])

    def _valid_state(self, s) -> bool:
        self.n_checks += 1
        return bool(self.checker.valid(self._state(s)[None])[0])

    def _valid_edge(self, a: np.ndarray, b: np.ndarray) -> bool:
        # the states of ``edge_states`` in the compiled checker: the end state first, then a coarse pass spread
        # over the edge (which stops most edges in collision after a few states), then the rest
        self.n_checks += 1
        d = b - a
        n = grid_count(math.sqrt(float(d @ d)), self.settings.check_step)
        return self.checker.edge_valid(a, b, n, self.chunk)

    def _setup(self, seed: int):
        from ompl import base as ob
        from ompl import geometric as og
        from ompl import util as ou

        # Reseeding after the first problem makes OMPL log "random number generation already started"; the
        # objects built below all take their seeds after this call, which makes the problem reproducible.
        ou.setLogLevel(ou.LOG_NONE)
        ou.RNG.setSeed(int(seed))
        ou.setLogLevel(ou.LOG_WARN)
        space = ob.RealVectorStateSpace(self.dof)
        bounds = ob.RealVectorBounds(self.dof)
        for i in range(self.dof):
            bounds.setLow(i, float(self.lo[i]))
            bounds.setHigh(i, float(self.hi[i]))
        space.setBounds(bounds)
        ss = og.SimpleSetup(space)
        ss.setStateValidityChecker(self._valid_state)
        si = ss.getSpaceInformation()
        si.setStateValidityCheckingResolution(self.settings.check_step / space.getMaximumExtent())
        mv = None
        if self.batched:
            outer = self

            class BatchedMotionValidator(ob.MotionValidator):
                def checkMotion(self, s1, s2, *rest):  # noqa: N802 (OMPL's name)
                    return outer._valid_edge(outer._state(s1), outer._state(s2))

            mv = BatchedMotionValidator(si)
            si.setMotionValidator(mv)
        planner = og.RRTConnect(si)
        if self.settings.range > 0:
            planner.setRange(self.settings.range)
        ss.setPlanner(planner)
        return space, ss, si, mv

    # -- one problem ---------------------------------------------------------------------------------------
    def _onto_bounds(self, q: np.ndarray, tol: float = 1e-6) -> np.ndarray:
        """``q`` with the values within ``tol`` outside a bound moved onto it (larger excesses are kept)."""
        q = np.where((q < self.lo) & (q >= self.lo - tol), self.lo, q)
        return np.where((q > self.hi) & (q <= self.hi + tol), self.hi, q)

    def plan(self, q_start: np.ndarray, q_goal: np.ndarray, seed: int) -> PlanResult:
        t0 = time.perf_counter()
        # a configuration on a joint limit that went through float32 (the contexts' tensors) lies just outside the
        # float64 bounds, which OMPL rejects, searching to its time limit: rounding-sized excesses go onto the bound
        q_start, q_goal = (self._onto_bounds(np.asarray(q, dtype=np.float64)) for q in (q_start, q_goal))
        ends = self.checker.valid(np.stack([q_start, q_goal]))
        if not ends[0] or not ends[1]:
            status = "invalid_start" if not ends[0] else "invalid_goal"
            return PlanResult(False, status, time.perf_counter() - t0)
        from ompl import base as ob
        from ompl import geometric as og

        space, ss, si, mv = self._setup(seed)
        try:
            a, g = space.allocState(), space.allocState()
            for i in range(self.dof):
                a[i] = float(q_start[i])
                g[i] = float(q_goal[i])
            ss.setStartAndGoalStates(a, g)
            self.n_checks = 0
            if self.settings.max_checks > 0:
                # evaluated by the planner at every iteration (no period, so no timer thread): the same work everywhere
                ptc = ob.plannerOrTerminationCondition(
                    ob.timedPlannerTerminationCondition(self.settings.time_limit),
                    ob.PlannerTerminationCondition(self._exhausted),
                )
                status = ss.solve(ptc)
            else:
                status = ss.solve(self.settings.time_limit)
            t_solve = time.perf_counter() - t0
            solve_checks = self.n_checks
            # only an exact solution counts (bool(status) is also true for an approximate one)
            if status.getStatus() != ob.PlannerStatus.EXACT_SOLUTION:
                reason = "budget" if self.settings.max_checks > 0 and self._exhausted() else "timeout"
                stats = {"solve_s": t_solve, "solve_checks": solve_checks, "checks": self.n_checks}
                return PlanResult(False, reason, time.perf_counter() - t0, stats=stats)
            path = ss.getSolutionPath()
            if self.settings.simplify == "max":
                og.PathSimplifier(si).simplifyMax(path)
            vertices = np.array([self._state(s) for s in path.getStates()])
            del path
        finally:
            del ss, si, mv, space
        dense = resample_path(vertices, self.n_points, self.settings.check_step, self.settings.resample)
        dense[0], dense[-1] = q_start, q_goal  # exact ends (OMPL copies them, this keeps them bit-identical)
        if self.store_dtype is not None:
            dense = dense.astype(self.store_dtype).astype(np.float64)
        ok = path_valid(self.checker, dense, self.settings.check_step)
        el = time.perf_counter() - t0
        stats = {"solve_s": t_solve, "n_vertices": len(vertices), "solve_checks": solve_checks, "checks": self.n_checks}
        if not ok:
            return PlanResult(False, "post_check", el, None, len(vertices), stats)
        return PlanResult(True, "ok", el, dense, len(vertices), stats)


_PLANNERS: dict[tuple, JointSpacePlanner] = {}
_MAX_PLANNERS = 16  # scenes with obstacles given at plan time come and go: keep the most recent ones


def plan_path(
    task,
    env,
    q_start: np.ndarray,
    q_goal: np.ndarray,
    *,
    time_limit: float | None = None,
    seed: int = 0,
    clearance: float | None = None,
    check_step: float | None = None,
    n_points: int | None = None,
) -> np.ndarray | None:
    """One RRTConnect path (n_points, dof) in a task environment, as the dataset generator plans it (sphere
    model with the task's clearance, simplifyMax, resampling); None when no valid path was found.

    ``env`` is ``task.env(...)`` or one derived from it with obstacles given at plan time. The planner of each
    (task, scene, settings) is built once per process.
    """
    cl = task.spec.collision.clearance if clearance is None else float(clearance)
    settings = PlannerSettings(
        time_limit=task.spec.data.planner_time_limit if time_limit is None else float(time_limit),
        check_step=default_check_step(task) if check_step is None else float(check_step),
    )
    n = task.spec.trajectory.n_points if n_points is None else int(n_points)
    key = (task.name, task.file_hash, env.key, cl, settings, n)
    if key not in _PLANNERS:
        checker = SphereChecker(task, clearance=cl, env=env)
        while len(_PLANNERS) >= _MAX_PLANNERS:
            _PLANNERS.pop(next(iter(_PLANNERS)))
        _PLANNERS[key] = JointSpacePlanner(checker, settings, n)
    r = _PLANNERS[key].plan(q_start, q_goal, problem_seed("plan_path", seed))
    return r.path if r.success else None
