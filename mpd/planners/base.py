"""The planner interface: every method of the paper is a :class:`Planner` (one file each) in ``PLANNERS``.

A planner turns one context (start configuration and goal configuration or goal end-effector pose) into a batch of
trajectories. Only :meth:`Planner.plan` is timed; validity is decided afterwards by the ground-truth checker
(``mpd.metrics``), never by the planner itself.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import ClassVar

import torch

from mpd.device import synchronize
from mpd.models.normalizer import Normalizer
from mpd.planners.settings import PlannerSettings
from mpd.trajectory import Dense, LinearTrajectory

PLANNERS: dict[str, type[Planner]] = {}


def register(cls: type[Planner]) -> type[Planner]:
    """Class decorator: make a planner available by its ``name``."""
    if cls.name in PLANNERS:
        raise ValueError(f"planner {cls.name!r} registered twice")
    PLANNERS[cls.name] = cls
    return cls


@dataclass
class Context:
    """One planning problem. ``q_goal`` is None for end-effector-goal tasks (models must not peek at the dataset's
    goal configuration there); ``ee_pos``/``ee_rot`` are None for joint-goal tasks. ``q_goal_ref`` is a goal
    configuration that reaches the end-effector goal (the dataset's, i.e. inverse kinematics done before planning):
    the baselines that need a goal configuration use it, as the authors' do (GPprior+Cost); None: they solve IK."""

    q_start: torch.Tensor
    q_goal: torch.Tensor | None = None
    ee_pos: torch.Tensor | None = None
    ee_rot: torch.Tensor | None = None
    q_goal_ref: torch.Tensor | None = None

    def to(self, device, dtype=torch.float32) -> Context:
        f = lambda x: None if x is None else x.to(device=device, dtype=dtype)  # noqa: E731
        return Context(f(self.q_start), f(self.q_goal), f(self.ee_pos), f(self.ee_rot), f(self.q_goal_ref))

    @property
    def ee_goal(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        return None if self.ee_pos is None else (self.ee_pos, self.ee_rot)


@dataclass
class HistoryStep:
    """A snapshot of the batch during planning (a denoising or optimization step), free rows in raw units."""

    label: str
    step: int
    free: torch.Tensor


@dataclass
class PlanResult:
    free: torch.Tensor  # (B, n_free, dof) free parameter rows, raw units
    control_points: torch.Tensor  # (B, n_params, dof) all rows
    dense: Dense  # (B, n_points, dof) positions and phase derivatives
    timings: dict[str, float]  # seconds: total, sampling, cost_gradient, cost/<name>, ik, rrt ...
    history: list[HistoryStep] | None = None
    info: dict = field(default_factory=dict)


class Timer:
    """Accumulates wall time per key; synchronizes the device before reading the clock."""

    def __init__(self, device: torch.device):
        self.device = device
        self.times: dict[str, float] = {}

    @contextmanager
    def __call__(self, key: str):
        synchronize(self.device)
        t = time.perf_counter()
        try:
            yield
        finally:
            synchronize(self.device)
            self.times[key] = self.times.get(key, 0.0) + time.perf_counter() - t

    def add(self, key: str, seconds: float) -> None:
        self.times[key] = self.times.get(key, 0.0) + seconds


class Planner:
    """Base class. Subclasses set ``name`` (registry key), ``label`` (for figures) and ``model_kind``."""

    name: ClassVar[str] = ""
    label: ClassVar[str] = ""
    model_kind: ClassVar[str | None] = None  # "diffusion" | "cvae" | None
    uses_cost: ClassVar[bool] = True
    # experiment axes that do not change what this planner does (collapsed in the spec matrix)
    unused_axes: ClassVar[tuple[str, ...]] = ()
    parametrizations: ClassVar[tuple[str, ...]] = ("bspline", "waypoints")

    @classmethod
    def unsupported(cls, params: dict) -> str | None:
        """Why a combination of experiment axis values cannot run with this planner (None when it can)."""
        p = params.get("parametrization")
        if p is not None and p not in cls.parametrizations:
            return f"{cls.label} supports only the {' / '.join(cls.parametrizations)} parametrization"
        return None

    def __init__(
        self,
        task,
        env,
        settings: PlannerSettings,
        parametrization: LinearTrajectory,
        model=None,
        device: torch.device | str = "cpu",
        normalizer: Normalizer | None = None,
    ):
        if self.model_kind is not None and model is None:
            raise ValueError(f"planner {self.name!r} needs a trained {self.model_kind} model")
        self.task = task
        self.env = env
        self.settings = settings
        self.param = parametrization
        self.device = torch.device(device)
        # a model loaded elsewhere (a CPU model given to a planner on a GPU) is used on the planner's device
        self.model = model.to(self.device) if hasattr(model, "to") else model
        self.robot = task.robot
        self.cost = None
        if self.uses_cost:
            from mpd.costs import CostFunction

            self.cost = CostFunction(
                task,
                parametrization,
                env,
                preset=settings.cost_preset,
                sdf_mode=settings.sdf_mode,
                profile=True,
            )
        # the unit-normalized space of free control points where guidance and every "+Cost" optimization act, and
        # whose range [-1, 1] every output is clipped to: a model's data range; for a planner without a model, the
        # data range it is given (the runner passes the dataset's, as the authors' baselines use it), else the
        # joint limits
        if model is not None:
            self.normalizer = model.x_normalizer
        elif normalizer is not None:
            self.normalizer = normalizer
        else:
            self.normalizer = Normalizer(task.robot.q_min.double().numpy(), task.robot.q_max.double().numpy())

    def use_environment(self, env) -> None:
        """Plan in another scene of the same task from now on (e.g. ``self.env.with_obstacles(...)``): what the
        planner checks and what its collision cost sees. Nothing else is rebuilt."""
        if env.dim != self.env.dim or env.spec is not self.env.spec:
            raise ValueError(f"{env!r} is not a scene of task {self.task.name}")
        self.env = env
        if self.cost is not None:
            self.cost.env = env

    # -- helpers shared by the planners ---------------------------------------------------------------------
    def cost_grad_fn(self, ctx: Context, timer: Timer) -> Callable[[torch.Tensor], torch.Tensor]:
        """x (normalized free rows, (B, n_free, dof)) -> dC/dx, timing every call and each cost."""
        q_start, q_goal, ee = ctx.q_start, ctx.q_goal, ctx.ee_goal

        def grad(x: torch.Tensor) -> torch.Tensor:
            with timer("cost_gradient"):
                free = self.normalizer.unnormalize(x)
                B = free.shape[0]
                ee_b = None if ee is None else (ee[0].expand(B, 3), ee[1].expand(B, 3, 3))
                res = self.cost(
                    free,
                    q_start.expand(B, -1),
                    None if q_goal is None else q_goal.expand(B, -1),
                    ee_goal=ee_b,
                )
                g = self.normalizer.grad_to_normalized(res.grad, x)
            for k, v in (res.timings or {}).items():
                timer.add(f"cost/{k}", v)
            timer.times["cost_gradient_calls"] = timer.times.get("cost_gradient_calls", 0) + 1
            return g

        return grad

    def finish(self, free: torch.Tensor, ctx: Context, timer: Timer, history=None, **info) -> PlanResult:
        B = free.shape[0]
        qs = ctx.q_start.expand(B, -1)
        qg = None if ctx.q_goal is None else ctx.q_goal.expand(B, -1)
        dense = self.param.dense(free, qs, qg)
        return PlanResult(free, self.param.full(free, qs, qg), dense, dict(timer.times), history, info)

    def plan(self, ctx: Context, n_samples: int, seed: int, record_history: bool = False) -> PlanResult:
        raise NotImplementedError


def model_context(ctx: Context) -> dict[str, torch.Tensor]:
    """The raw context fields a trained model is conditioned on."""
    if ctx.ee_pos is not None:
        return {"q_start": ctx.q_start, "ee_pos": ctx.ee_pos, "ee_rot": ctx.ee_rot}
    return {"q_start": ctx.q_start, "q_goal": ctx.q_goal}
