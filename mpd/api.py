"""mpd as a library: load a planner with a shipped prior, plan around the obstacles you see.

    import mpd

    planner = mpd.load_planner("EnvWarehouse-RobotPanda")            # MPD with the task's default shipped prior
    plan = planner.plan(q_start, mpd.Pose([0.4, 0.3, 0.6], [0, 1, 0, 0]),
                        obstacles=[mpd.Box([0.5, 0.0, 0.4], [0.05, 0.2, 0.1]), mpd.Sphere([0.3, 0.3, 0.7], 0.08)],
                        n_samples=100, seed=0)
    plan.q[plan.best]        # (128, 7) joint positions of the best valid trajectory, at times plan.t

Obstacles given at plan time enter both the collision cost the planner is guided by and the ground-truth checker
that decides ``plan.valid``. Every input is checked before any work; a problem raises :class:`PlanningInputError`
with one line that names the argument.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mpd.envs.primitives import Primitive, quat_wxyz_to_matrix
from mpd.planners.inputs import PlanningInputError, as_array, check_configuration, float32_within, shape_of

# The network path a planner of the API runs by default: compiled (torch.compile, frozen weights) in bf16 where the
# device computes it natively, else fp32 (PlannerSettings.network_precision = "auto"). Each batch size compiles once
# per process, outside the timed plan (MotionPlanner.warmup); inductor's on-disk cache makes later processes faster.
from mpd.planners.settings import FAST_SETTINGS, fast_enabled


@dataclass(frozen=True)
class Sphere:
    """A spherical obstacle: centre (2 or 3 coordinates, as the task's workspace) and radius, in metres, in the
    task's world frame."""

    center: Sequence[float]
    radius: float


@dataclass(frozen=True)
class Box:
    """A box obstacle: centre and half extents (2 or 3 each), in metres, in the task's world frame; ``rotation`` maps
    box-frame vectors to the world: a (D, D) matrix, or a unit quaternion (w, x, y, z) in 3-D; None is the identity.
    Boxes get the task's corner radius (``environment.box_corner_radius``), like its own."""

    center: Sequence[float]
    half_extents: Sequence[float]
    rotation: Any = None


@dataclass(frozen=True)
class Pose:
    """An end-effector goal: position (3,) in metres and orientation as a unit quaternion (w, x, y, z)."""

    position: Sequence[float]
    quaternion: Sequence[float] = (1.0, 0.0, 0.0, 0.0)


@dataclass
class MotionPlan:
    """What :meth:`MotionPlanner.plan` returns: ``n_samples`` trajectories of one problem, dense and timed.

    Arrays are numpy float64 (:meth:`to_torch` for tensors): ``t`` (n_points,) seconds; ``q``, ``dq``, ``ddq``
    (n_samples, n_points, dof) positions, velocities, accelerations; ``control_points`` (n_samples, n_params, dof).
    ``valid`` (n_samples,) by the ground-truth checker (exact signed distance of the task's scene *and* the
    obstacles given to this plan, self collision, position / velocity / acceleration limits), with its parts
    ``collision_free`` and ``limits_ok``. ``cost`` (n_samples,) the task's weighted cost (the one MPD is guided by,
    same scene), ``cost_terms`` each cost unweighted. ``best`` the index of the best valid trajectory (the paper's
    rule: shortest path, or nearest the end-effector goal) or None when none is valid. ``metrics`` the paper's
    per-problem metrics (success, fraction valid, Vendi, ...), ``timings`` seconds (``total`` is the planner's time;
    ``check`` the checker's after it), ``provenance`` what made it (task file hash, model identity and source,
    settings, obstacles digest, seed, versions)."""

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    control_points: np.ndarray
    valid: np.ndarray
    collision_free: np.ndarray
    limits_ok: np.ndarray
    cost: np.ndarray
    cost_terms: dict[str, np.ndarray]
    best: int | None
    metrics: dict[str, float]
    timings: dict[str, float]
    provenance: dict[str, Any]
    # with record_history: (label, dense positions (n_samples, n_points, dof), valid (n_samples,)) per step
    history: list[tuple[str, np.ndarray, np.ndarray]] | None = field(default=None, repr=False)
    _task: Any = field(default=None, repr=False)
    _env: Any = field(default=None, repr=False)

    @property
    def n_samples(self) -> int:
        return int(self.q.shape[0])

    def to_torch(self) -> dict[str, torch.Tensor]:
        """The arrays as tensors (float64; bool for the flags)."""
        keys = ("t", "q", "dq", "ddq", "control_points", "valid", "collision_free", "limits_ok", "cost")
        return {k: torch.from_numpy(np.asarray(getattr(self, k))) for k in keys}

    def figure(self, path: str | Path | None = None, title: str | None = None):
        """The paper-style figure of this plan: the scene with every trajectory (valid ones solid) and the joints'
        position / velocity / acceleration against time; written to ``path`` (.png or .pdf) when given."""
        from mpd.viz.scene import trajectory_figure

        title = title or f"{self.provenance.get('method')} - {self._task.name}"
        return trajectory_figure(self._task, self._env, self.q, self.dq, self.ddq, self.valid, out=path, title=title)

    def recording(self, path: str | Path) -> Path:
        """A Rerun recording (.rrd) of this plan: the scene, the trajectories, the best one animated, and with
        ``record_history=True`` the batch at every denoising step; open it with ``rerun PATH``."""
        from mpd.viz.recording import record_history

        hist: dict[str, Any] = {"q": self.q, "valid": self.valid}
        if self.history:
            hist.update(
                steps_q=np.stack([q for _, q, _ in self.history]),
                steps_valid=np.stack([v for _, _, v in self.history]),
                steps_label=np.array([label for label, _, _ in self.history]),
            )
        params = {k: self.provenance.get(k) for k in ("method", "extra_objects", "rotation_deg", "seed")}
        return record_history(path, self._task, params, hist, env=self._env)

    def __repr__(self) -> str:
        best = "none valid" if self.best is None else f"best #{self.best}"
        return (
            f"MotionPlan({self.provenance.get('method')} on {self.provenance.get('task')}: {self.n_samples} "
            f"trajectories, {int(self.valid.sum())} valid, {best}, {self.timings.get('total', float('nan')):.3f} s)"
        )


class MotionPlanner:
    """One method of the paper on one task, ready to plan many problems (see :func:`load_planner`)."""

    def __init__(self, planner, task, method: str, model, extra_objects: bool, rotation_deg: float):
        self._planner = planner
        self.task = task
        self.method = method
        self.model = model
        self._base_env = planner.env
        self._extra_objects = extra_objects
        self._rotation_deg = rotation_deg
        self._scenes: dict[str, Any] = {}  # obstacles digest -> environment (its grids stay built)
        self._scoring = None
        self._git: str | None = None

    # -- description ---------------------------------------------------------------------------------------------
    @property
    def settings(self):
        """The planner's :class:`mpd.planners.PlannerSettings`."""
        return self._planner.settings

    @property
    def parametrization(self) -> str:
        """The trajectory's parametrization: ``"bspline"`` or ``"waypoints"``."""
        return self._planner.param.name

    @property
    def dof(self) -> int:
        return self.task.dof

    @property
    def goal_kind(self) -> str:
        """``"pose"`` (an end-effector goal: :class:`Pose`, a 4x4 matrix or a goal configuration) or ``"joints"``."""
        return "pose" if self.task.ee_goal else "joints"

    def __repr__(self) -> str:
        model = "" if self.model is None else f", model {self.model.meta.get('identity')}"
        param = "" if self.parametrization == "bspline" else f", {self.parametrization}"
        return f"MotionPlanner({self.method} on {self.task.name}{model}{param})"

    # -- inputs --------------------------------------------------------------------------------------------------
    def _obstacles(self, obstacles) -> list[Primitive]:
        if obstacles is None:
            return []
        if isinstance(obstacles, (Sphere, Box)):
            obstacles = [obstacles]
        if not isinstance(obstacles, (list, tuple)):
            raise PlanningInputError(
                "obstacles", f"is a {type(obstacles).__name__}, expected a list of mpd.Sphere and mpd.Box"
            )
        D = self.task.dim
        prims = []
        for i, o in enumerate(obstacles):
            name = f"obstacles[{i}]"
            if isinstance(o, Sphere):
                c = as_array(o.center, f"{name}.center", (D,))
                r = float(as_array(o.radius, f"{name}.radius", ()))
                if r <= 0:
                    raise PlanningInputError(f"{name}.radius", f"must be positive, got {r:g}")
                prims.append(Primitive("sphere", c, radius=r, name=name))
            elif isinstance(o, Box):
                c = as_array(o.center, f"{name}.center", (D,))
                h = as_array(o.half_extents, f"{name}.half_extents", (D,))
                if (h <= 0).any():
                    raise PlanningInputError(f"{name}.half_extents", f"must be positive, got {list(h)}")
                prims.append(Primitive("box", c, half_size=h, rotation=self._rotation(o.rotation, name), name=name))
            else:
                raise PlanningInputError(name, f"is a {type(o).__name__}, expected mpd.Sphere or mpd.Box")
        return prims

    def _rotation(self, rot, name: str) -> np.ndarray:
        D = self.task.dim
        if rot is None:
            return np.eye(D)
        shape = shape_of(rot)
        a = as_array(rot, f"{name}.rotation", shape if shape and len(shape) in (1, 2) else (D, D))
        if a.shape == (4,) and D == 3:
            q = as_array(a, f"{name}.rotation", (4,))
            if np.linalg.norm(q) < 1e-9:
                raise PlanningInputError(f"{name}.rotation", "the quaternion (w, x, y, z) has zero length")
            return quat_wxyz_to_matrix(q)
        m = as_array(a, f"{name}.rotation", (D, D))
        if not np.allclose(m @ m.T, np.eye(D), atol=1e-6) or np.linalg.det(m) < 0:
            raise PlanningInputError(f"{name}.rotation", "is not a rotation matrix (orthonormal, determinant +1)")
        return m

    def _goal(self, goal) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """(goal configuration or None, goal position or None, goal rotation or None)."""
        dof = self.dof
        shape = shape_of(goal)
        if isinstance(goal, Pose) or shape == (4, 4):
            if not self.task.ee_goal:
                raise PlanningInputError(
                    "goal", f"task {self.task.name} takes a joint configuration ({dof} values), not a pose"
                )
            if isinstance(goal, Pose):
                p = as_array(goal.position, "goal.position", (3,))
                q = as_array(goal.quaternion, "goal.quaternion", (4,))
                if np.linalg.norm(q) < 1e-9:
                    raise PlanningInputError("goal.quaternion", "has zero length (expected a unit (w, x, y, z))")
                return None, p, quat_wxyz_to_matrix(q)
            m = as_array(goal, "goal", (4, 4))
            r = m[:3, :3]
            if not np.allclose(m[3], [0, 0, 0, 1]) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
                raise PlanningInputError("goal", "a 4x4 goal must be a homogeneous transform (rotation, last row 0001)")
            return None, m[:3, 3].copy(), r.copy()
        if shape != (dof,):
            kind = f"a joint configuration ({dof} values)" + (
                ", an mpd.Pose or a 4x4 transform" if self.task.ee_goal else ""
            )
            got = f"has shape {shape}" if shape is not None else f"{goal!r} is not an array of numbers"
            raise PlanningInputError("goal", f"{got}, expected {kind}")
        return as_array(goal, "goal", (dof,)), None, None

    def scene(self, obstacles=None):
        """The environment a plan with these obstacles sees (built once per obstacle set and kept)."""
        from mpd.envs.environment import obstacles_digest

        prims = self._obstacles(obstacles)
        if not prims:
            return self._base_env
        key = obstacles_digest(prims)
        if key not in self._scenes:
            if len(self._scenes) >= 8:  # keep the grids of the most recent obstacle sets only
                self._scenes.pop(next(iter(self._scenes)))
            self._scenes[key] = self._base_env.with_obstacles(prims)
        return self._scenes[key]

    def check(self, plan: MotionPlan, obstacles: Sequence[Sphere | Box] | None = None) -> np.ndarray:
        """Validity (n_samples,) of a plan's trajectories in this task's scene with ``obstacles`` (e.g. obstacles
        seen after it was planned), by the same ground-truth checker as :attr:`MotionPlan.valid`."""
        from mpd.collision import CollisionChecker

        env = self.scene(obstacles)
        t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
        return CollisionChecker(self.task, env=env).trajectories(t(plan.q), t(plan.dq), t(plan.ddq)).valid.numpy()

    # -- planning ------------------------------------------------------------------------------------------------
    def warmup(self, n_samples: int = 100) -> float:
        """Compile the denoising network for batches of ``n_samples`` (done by the first plan of that size
        otherwise, before its clock starts); returns the seconds it took (0 when there is nothing to compile)."""
        warm = getattr(self._planner, "warmup", None)
        return warm(n_samples) if warm is not None else 0.0

    def plan(
        self,
        q_start,
        goal,
        *,
        obstacles: Sequence[Sphere | Box] | None = None,
        n_samples: int = 100,
        seed: int = 0,
        record_history: bool = False,
    ) -> MotionPlan:
        """Plan ``n_samples`` trajectories from ``q_start`` to ``goal`` around the task's scene and ``obstacles``.

        ``goal``: a joint configuration (dof,), or for an end-effector-goal task an :class:`Pose` or a 4x4 transform
        (a configuration there is turned into its end-effector pose, and given to the baselines that need a goal
        configuration). ``seed`` makes the plan repeatable. ``record_history``: keep the batch after every denoising
        or optimization step (``MotionPlan.history``)."""
        from mpd.collision import CollisionChecker
        from mpd.metrics import evaluate
        from mpd.planners import Context

        if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 1:
            raise PlanningInputError("n_samples", f"must be a positive integer, got {n_samples!r}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise PlanningInputError("seed", f"must be a non-negative integer, got {seed!r}")
        qs = as_array(q_start, "q_start", (self.dof,))
        q_goal, p_goal, r_goal = self._goal(goal)
        env = self.scene(obstacles)
        checker = CollisionChecker(self.task, env=env)
        check_configuration(self.task, qs, "q_start", checker)
        if q_goal is not None:
            check_configuration(self.task, q_goal, "goal", checker)
        f32 = lambda a: None if a is None else torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
        # the configurations in float32, a configuration on a joint limit kept on it (not rounded beyond)
        lo, hi = self.task.robot.q_min.double().numpy(), self.task.robot.q_max.double().numpy()
        fq = lambda a: None if a is None else torch.as_tensor(float32_within(a, lo, hi))  # noqa: E731
        if self.task.ee_goal:
            if q_goal is not None:
                p, r = self.task.robot.ee_pose(torch.as_tensor(q_goal, dtype=torch.float64))
                p_goal, r_goal = p.numpy(), r.numpy()
            ctx = Context(fq(qs), None, f32(p_goal), f32(r_goal), q_goal_ref=fq(q_goal))
        else:
            ctx = Context(fq(qs), fq(q_goal))

        t0 = time.perf_counter()
        self._planner.use_environment(env)
        if env.obstacles and self._planner.cost is not None and self.settings.sdf_mode != "analytic":
            env.grid("extra")  # the first plan with these obstacles builds their grid here, outside the plan's clock
        scene_s = time.perf_counter() - t0
        warm_s = self.warmup(int(n_samples))
        res = self._planner.plan(ctx.to(self._planner.device), int(n_samples), int(seed), record_history)
        t1 = time.perf_counter()
        d = res.dense
        dense = type(d)(d.q.cpu().double(), d.dq_ds.cpu().double(), d.ddq_ds2.cpu().double(), d.duration)
        ee = None if p_goal is None else (torch.as_tensor(p_goal), torch.as_tensor(r_goal))
        metrics, val, best = evaluate(
            checker, dense, q_goal=None if self.task.ee_goal else torch.as_tensor(q_goal), ee_goal=ee
        )
        cost = self._cost(env, res.free, ctx)
        timings = {**res.timings, "check": time.perf_counter() - t1, "scene": scene_s, "warmup": warm_s}
        n = dense.q.shape[1]
        history = None
        if res.history is not None:
            history = []
            for h in res.history:
                B = h.free.shape[0]
                qs_b = ctx.q_start.to(h.free).expand(B, -1)
                qg_b = None if ctx.q_goal is None else ctx.q_goal.to(h.free).expand(B, -1)
                hq = self._planner.param.dense(h.free, qs_b, qg_b).q.detach().cpu().double()
                history.append((f"{h.label} {h.step}", hq.numpy(), checker.trajectories(hq).valid.numpy()))
        return MotionPlan(
            t=np.linspace(0.0, float(d.duration), n),
            q=dense.q.numpy(),
            dq=dense.dq_dt.numpy(),
            ddq=dense.ddq_dt2.numpy(),
            control_points=res.control_points.detach().cpu().double().numpy(),
            valid=val.valid.numpy(),
            collision_free=val.collision_free.numpy(),
            limits_ok=val.limits_ok.numpy(),
            cost=cost.total.detach().cpu().double().numpy(),
            cost_terms={k: v.detach().cpu().double().numpy() for k, v in cost.values.items()},
            best=best,
            metrics={k: float(v) for k, v in metrics.items()},
            timings=timings,
            provenance=self._provenance(env, seed, res.info),
            history=history,
            _task=self.task,
            _env=env,
        )

    def _cost(self, env, free: torch.Tensor, ctx):
        from mpd.costs import CostFunction

        p = self._planner
        if p.cost is not None:
            cost = p.cost
        else:
            if self._scoring is None:
                s = p.settings
                self._scoring = CostFunction(self.task, p.param, env, preset=s.cost_preset, sdf_mode=s.sdf_mode)
            cost = self._scoring
            cost.env = env
        B = free.shape[0]
        c = ctx.to(free.device)
        ee = None if c.ee_pos is None else (c.ee_pos.expand(B, 3), c.ee_rot.expand(B, 3, 3))
        with torch.no_grad():
            return cost(free, c.q_start.expand(B, -1), None if c.q_goal is None else c.q_goal.expand(B, -1), ee)

    def _provenance(self, env, seed: int, info: dict) -> dict[str, Any]:
        import mpd
        from mpd.envs.environment import obstacles_digest
        from mpd.provenance import git_state

        if self._git is None:
            self._git = git_state()[0]
        m = self.model
        return {
            "task": self.task.name,
            "task_sha256": self.task.file_hash,
            "method": self.method,
            "model_identity": None if m is None else m.meta.get("identity"),
            "model_source": None if m is None else m.meta.get("source"),
            "model_file": None if m is None else str(m.path),
            "parametrization": self.parametrization,
            "extra_objects": self._extra_objects,
            "rotation_deg": self._rotation_deg,
            "obstacles": len(env.obstacles),
            "obstacles_digest": obstacles_digest(env.obstacles) if env.obstacles else None,
            "seed": int(seed),
            "settings": dict(self.settings.__dict__),
            "device": str(self._planner.device),
            "mpd": mpd.__version__,
            "git_commit": self._git or "unknown",
            "torch": torch.__version__,
            **{k: v for k, v in info.items() if k.startswith("network_")},
        }


def load_planner(
    task: str | Path,
    method: str = "mpd",
    *,
    model: str | Path | None = None,
    parametrization: str | None = None,
    preset: str = "official",
    extra_objects: bool = False,
    rotation_deg: float = 0.0,
    fast: bool = True,
    device: str | torch.device | None = None,
    **settings: Any,
) -> MotionPlanner:
    """A planner of ``method`` (any name of ``mpd planners list``: mpd, dprior, dprior-cost, cvae, cvae-cost, gp-cost,
    rrtconnect-cost, or package.module:Class) for ``task`` (a task name or a task file).

    ``model``: None for the task's default shipped prior (the one trained longest), a model identity or a prefix of
    one (the cache, then the shipped priors), ``"latest"`` (the newest trained here) or a checkpoint path; methods
    without a model ignore it. ``parametrization``: ``"bspline"`` or ``"waypoints"``; None takes the named model's
    own (a checkpoint path or an identity), ``"bspline"`` for the default and latest. ``extra_objects`` /
    ``rotation_deg``: the task's own scene variants. ``fast``: the compiled network in bf16 where the CPU has it
    (:data:`FAST_SETTINGS`), on a device torch.compile can build kernels for (a CPU with a C++ compiler);
    ``fast=False`` (or the environment variable ``MPD_COMPILE=0``) is the eager fp32 network. ``settings``:
    :class:`mpd.planners.PlannerSettings` fields, e.g. ``guide_lr=0.5``."""
    from mpd.models.find import find_model
    from mpd.planners import get_planner_class, make_planner
    from mpd.planners.validation import check_task_settings
    from mpd.schema import ConfigError
    from mpd.tasks import load_task

    try:
        t = load_task(task)
    except ConfigError as e:
        raise PlanningInputError("task", str(e)) from None
    try:
        cls = get_planner_class(method)
    except ValueError as e:
        raise PlanningInputError("method", str(e)) from None
    if preset not in ("official", "paper"):
        raise PlanningInputError("preset", f"{preset!r} is not official or paper")
    check_task_settings(t)
    from mpd.device import default_device

    fast = fast and fast_enabled(device if device is not None else default_device())
    overrides = {**(FAST_SETTINGS if fast and cls.model_kind == "diffusion" else {}), **settings}
    from mpd.planners.settings import PlannerSettings

    known = set(PlannerSettings.__dataclass_fields__)
    unknown = sorted(set(settings) - known)
    if unknown:
        raise PlanningInputError(unknown[0], f"is not a planner setting (known: {', '.join(sorted(known))})")
    from mpd.trajectory import PARAMETRIZATIONS

    if parametrization is not None and parametrization not in PARAMETRIZATIONS:
        raise PlanningInputError("parametrization", f"{parametrization!r} is not {' or '.join(PARAMETRIZATIONS)}")
    loaded = None
    if cls.model_kind is not None:
        try:
            loaded = find_model(t.name, cls.model_kind, parametrization, model, device=device)
        except ConfigError as e:
            raise PlanningInputError("model", e.detail) from None
        parametrization = loaded.parametrization
    parametrization = parametrization or "bspline"
    try:
        planner = make_planner(
            method,
            t,
            extra_objects=extra_objects,
            rotation_deg=rotation_deg,
            preset=preset,
            overrides=overrides,
            parametrization=parametrization,
            model=loaded,
            device=device,
        )
    except (ValueError, TypeError) as e:
        raise PlanningInputError("settings", str(e)) from None
    return MotionPlanner(planner, t, method, loaded, extra_objects, rotation_deg)


__all__ = [
    "FAST_SETTINGS",
    "Box",
    "MotionPlan",
    "MotionPlanner",
    "Pose",
    "PlanningInputError",
    "Sphere",
    "load_planner",
]
