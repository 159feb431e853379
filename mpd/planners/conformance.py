"""The conformance checks every planner passes (the built-in ones and a user's own): ``mpd planners check NAME``.

A planner conforms when, on a small 2-D task, it is a :class:`~mpd.planners.base.Planner` subclass with a name
and a label, builds through :func:`~mpd.planners.make_planner`, and :meth:`~mpd.planners.base.Planner.plan`
returns a :class:`~mpd.planners.base.PlanResult` whose shapes match the parametrization for any batch size, whose
trajectories are finite and start (and, with a goal configuration, end) at the context, that is the same for the
same seed, with a ``total`` time no longer than the call itself and finite, non-negative timings, and whose
recorded history (when asked for) holds batches of the same shape. The first check that fails raises
:class:`PlannerCheckError` with one line naming the planner, the check and what was found.

Planners that need a model get a small randomly initialized one: the structure does not depend on the weights.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from mpd.planners import Context, PlanResult, get_planner_class, make_planner
from mpd.planners.base import HistoryStep, Planner

CHECK_TASK = "EnvSimple2D-RobotPointMass2D"
# a collision-free start and goal of CHECK_TASK
_START, _GOAL = [-0.2, -0.9], [-0.2, 0.9]
_MODEL_KINDS = (None, "diffusion", "cvae")


class PlannerCheckError(ValueError):
    """A planner breaks the interface. The message names the planner and the check."""


@dataclass
class CheckReport:
    planner: str
    label: str
    checks: list[str]


def random_model(task, kind: str, parametrization: str = "bspline", seed: int = 0):
    """A small randomly initialized model of ``kind`` for ``task`` (for structure checks, not for planning)."""
    from mpd.models.checkpoint import LoadedModel, build_network
    from mpd.models.context import context_keys
    from mpd.models.normalizer import Normalizer
    from mpd.tasks.spec import ModelSpec
    from mpd.trajectory import make_parametrization

    small = ModelSpec(unet_dim=8, unet_dim_mults=[1, 2], context_dim=8, context_layers=1, time_emb_dim=8)
    param = make_parametrization(task, parametrization)
    ctx_kind = "goal_ee_pose" if task.ee_goal else "goal_joint_position"
    torch.manual_seed(seed)
    net = build_network(kind, task.dof, param.n_free, ctx_kind, small).eval().requires_grad_(False)
    lo, hi = task.robot.q_min.float(), task.robot.q_max.float()
    norms = {k: Normalizer(lo, hi) for k in context_keys(ctx_kind) if k in ("q_start", "q_goal")}
    if task.ee_goal:
        norms["ee_pos"] = Normalizer(-torch.ones(3), torch.ones(3))
    meta = {
        "task_name": task.name,
        "parametrization": parametrization,
        "horizon": param.n_free,
        "dof": task.dof,
        "context_kind": ctx_kind,
    }
    return LoadedModel(kind, net, Normalizer(lo, hi), norms, meta, path=f"<random {kind}>")


def check_planner(ref: str, task_name: str = CHECK_TASK, n_samples: int = 6, seed: int = 3) -> CheckReport:
    """Run the conformance checks on the planner ``ref`` (a name, an entry point or ``package.module:Class``)."""
    from mpd.tasks import load_task

    checks: list[str] = []

    def fail(check: str, what: str) -> None:
        raise PlannerCheckError(f"planner {ref!r}: {check}: {what}")

    try:
        cls = get_planner_class(ref)
    except ValueError as e:
        raise PlannerCheckError(str(e)) from None
    for attr in ("name", "label"):
        if not isinstance(getattr(cls, attr, None), str) or not getattr(cls, attr):
            fail("class", f"{cls.__module__}.{cls.__qualname__}.{attr} must be a non-empty string")
    if cls.model_kind not in _MODEL_KINDS:
        fail("class", f"model_kind {cls.model_kind!r} is not one of {_MODEL_KINDS}")
    if not isinstance(cls.unused_axes, tuple) or not isinstance(cls.parametrizations, tuple):
        fail("class", "unused_axes and parametrizations must be tuples")
    if "bspline" not in cls.parametrizations:
        fail("class", "the checks (and every spec's default) use the bspline parametrization")
    checks.append("class: a Planner subclass with a name, a label and a model kind")

    task = load_task(task_name)
    model = random_model(task, cls.model_kind) if cls.model_kind else None

    def build() -> Planner:
        try:
            return make_planner(ref, task, model=model, device="cpu", overrides={"rrt_time_limit": 5.0})
        except Exception as e:  # noqa: BLE001 - the user's constructor: any failure is one line
            fail("construction", f"make_planner raised {type(e).__name__}: {e}")
        raise AssertionError  # unreachable

    planner = build()
    checks.append("construction: make_planner builds it on the training scene")
    ctx = Context(torch.tensor(_START), torch.tensor(_GOAL))

    def plan(p: Planner, n: int, record: bool) -> tuple[PlanResult, float]:
        t = time.perf_counter()
        try:
            res = p.plan(ctx, n, seed, record_history=record)
        except Exception as e:  # noqa: BLE001
            fail("plan", f"plan(ctx, {n}, seed={seed}) raised {type(e).__name__}: {e}")
        wall = time.perf_counter() - t
        if not isinstance(res, PlanResult):
            fail("plan", f"returned {type(res).__name__}, not a PlanResult (build it with self.finish(...))")
        return res, wall

    res, wall = plan(planner, n_samples, True)
    param = planner.param
    for b, r in ((n_samples, res), (1, plan(planner, 1, False)[0])):
        want = {
            "free": (b, param.n_free, task.dof),
            "control_points": (b, param.n_params, task.dof),
            "dense.q": (b, param.n_points, task.dof),
            "dense.dq_ds": (b, param.n_points, task.dof),
            "dense.ddq_ds2": (b, param.n_points, task.dof),
        }
        got = {
            "free": r.free,
            "control_points": r.control_points,
            "dense.q": r.dense.q,
            "dense.dq_ds": r.dense.dq_ds,
            "dense.ddq_ds2": r.dense.ddq_ds2,
        }
        for k, shape in want.items():
            x = got[k]
            if not isinstance(x, torch.Tensor) or tuple(x.shape) != shape:
                fail("shapes", f"{k} is {tuple(getattr(x, 'shape', ()))} for n_samples={b}, expected {shape}")
            if not torch.isfinite(x).all():
                fail("shapes", f"{k} holds NaN or inf values")
    checks.append(f"shapes: free, control points and dense trajectories for n_samples = {n_samples} and 1, finite")

    q = res.dense.q.double()
    if not torch.allclose(q[:, 0], ctx.q_start.double().expand_as(q[:, 0]), atol=1e-4):
        fail("boundary", f"trajectories start at {q[0, 0].tolist()}, not at q_start {ctx.q_start.tolist()}")
    if not torch.allclose(q[:, -1], ctx.q_goal.double().expand_as(q[:, -1]), atol=1e-4):
        fail("boundary", f"trajectories end at {q[0, -1].tolist()}, not at q_goal {ctx.q_goal.tolist()}")
    checks.append("boundary: every trajectory starts at q_start and ends at q_goal")

    again, _ = plan(build(), n_samples, True)
    if not torch.equal(res.free, again.free):
        diff = (res.free - again.free).abs().max().item()
        fail("determinism", f"two plans with seed {seed} differ (max |difference| {diff:.3g}); use the seed")
    checks.append("determinism: the same seed gives the same trajectories, bit for bit")

    t = res.timings
    if not isinstance(t, dict) or "total" not in t:
        fail("timings", f"timings must hold 'total' (seconds of the plan call), got {sorted(t) if t else t}")
    for k, v in t.items():
        if not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
            fail("timings", f"timings[{k!r}] = {v!r} is not a finite, non-negative number")
    if not 0 < t["total"] <= wall * 1.05 + 1e-3:  # measured inside the call: never longer than the call
        fail("timings", f"timings['total'] = {t['total']:.4g} s, but the plan call took {wall:.4g} s")
    checks.append("timings: 'total' present and within the call's wall time, every timing finite and >= 0")

    if res.history is not None:
        for h in res.history:
            if not isinstance(h, HistoryStep) or tuple(h.free.shape) != tuple(res.free.shape):
                fail("history", f"every history step must be a HistoryStep with free rows shaped {res.free.shape}")
        checks.append(f"history: {len(res.history)} recorded steps shaped like the result")
    return CheckReport(cls.name, cls.label, checks)


__all__ = ["CHECK_TASK", "CheckReport", "PlannerCheckError", "check_planner", "random_model"]
