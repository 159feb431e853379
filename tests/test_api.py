"""The Python API (mpd.load_planner / MotionPlanner.plan) on the shipped priors: obstacles given at plan time reach the
checker and the cost, the same as the task's own extra objects; every bad input fails first, in one line naming it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mpd
from mpd.collision import CollisionChecker
from mpd.tasks import load_task

TASK = "EnvSimple2D-RobotPointMass2D"
START, GOAL = [-0.8, -0.8], [0.8, 0.8]


@pytest.fixture(scope="module")
def planner():
    return mpd.load_planner(TASK, fast=False)


def test_the_default_model_is_the_shipped_prior_trained_longest(tmp_path, monkeypatch):
    from mpd.models.find import resolve_model, shipped_priors

    monkeypatch.setenv("MPD_CACHE", str(tmp_path))  # an empty cache: only the shipped priors exist
    pri = shipped_priors("EnvWarehouse-RobotPanda", "diffusion", "bspline")
    assert len(pri) == 2
    samples = [e["steps"] * e["training_spec"]["batch_size"] for e in pri]
    assert samples == sorted(samples, reverse=True)
    path, source = resolve_model("EnvWarehouse-RobotPanda", "diffusion", "bspline", None)
    assert source == "shipped" and pri[0]["identity"] in path.name
    # "latest" falls back to it with nothing trained here; an identity prefix finds a shipped prior too
    assert resolve_model("EnvWarehouse-RobotPanda", "diffusion", "bspline", "latest") == (path, "shipped")
    other = pri[1]["identity"]
    assert other in resolve_model("EnvWarehouse-RobotPanda", "diffusion", "bspline", other[:8])[0].name
    with pytest.raises(mpd.PlanningInputError, match=r"^model: no diffusion model .* identity 'ffff'"):
        mpd.load_planner("EnvWarehouse-RobotPanda", model="ffff")


def test_a_named_model_brings_its_own_parametrization():
    """A waypoint prior named by its path or its identity plans as waypoints without ``parametrization=``; the
    default stays the B-spline prior; a parametrization that contradicts the named model, or is no parametrization,
    fails in one line naming the argument."""
    from mpd.models.find import shipped_priors

    wp = shipped_priors(TASK, "diffusion", "waypoints")[0]  # the default: trained on the most samples
    for ref in (wp["path"], wp["identity"][:8]):
        p = mpd.load_planner(TASK, "dprior", model=ref, fast=False)
        assert p.parametrization == p.model.parametrization == "waypoints"
        assert p.model.meta["identity"] == wp["identity"]
        plan = p.plan(START, GOAL, n_samples=4, seed=0)
        assert np.asarray(plan.q).shape[0] == 4 and plan.provenance["parametrization"] == "waypoints"
        assert repr(p).endswith(", waypoints)")
    assert mpd.load_planner(TASK, "dprior", fast=False).parametrization == "bspline"
    with pytest.raises(mpd.PlanningInputError, match=r"^model: .*checkpoint is for parametrization 'waypoints'"):
        mpd.load_planner(TASK, "dprior", model=wp["path"], parametrization="bspline")
    with pytest.raises(mpd.PlanningInputError, match=r"^parametrization: 'spline' is not"):
        mpd.load_planner(TASK, "dprior", parametrization="spline")


def test_plan_shapes_timings_provenance_and_seed(planner):
    a = planner.plan(START, GOAL, n_samples=6, seed=3)
    b = planner.plan(np.array(START), torch.tensor(GOAL), n_samples=6, seed=3)
    n = load_task(TASK).spec.trajectory.n_points
    assert a.q.shape == a.dq.shape == a.ddq.shape == (6, n, 2) and a.t.shape == (n,)
    assert a.t[0] == 0 and a.t[-1] == pytest.approx(load_task(TASK).spec.trajectory.duration)
    np.testing.assert_allclose(a.q[:, 0], np.tile(START, (6, 1)), atol=1e-6)
    np.testing.assert_allclose(a.q[:, -1], np.tile(GOAL, (6, 1)), atol=1e-6)
    # velocities are the time derivative of the positions (finite differences of the dense samples)
    fd = np.gradient(a.q, a.t, axis=1)
    assert np.abs(fd[:, 2:-2] - a.dq[:, 2:-2]).max() < 0.02 * np.abs(a.dq).max()
    np.testing.assert_array_equal(a.q, b.q)
    assert a.cost.shape == (6,) and set(a.cost_terms) >= {"collision", "velocity"}
    assert a.timings["total"] > 0 and a.provenance["model_source"] == "shipped"
    assert a.provenance["task_sha256"] == load_task(TASK).file_hash and a.provenance["seed"] == 3
    assert (a.best is None) == (not a.valid.any())
    assert not np.array_equal(planner.plan(START, GOAL, n_samples=6, seed=4).q, a.q)


def _sphere_free(q: np.ndarray, centre, radius: float, robot_radius: float = 0.02) -> np.ndarray:
    """Per trajectory: every point keeps the robot's disc out of the sphere (independent of mpd's SDF code)."""
    return (np.linalg.norm(q - np.asarray(centre), axis=-1) - radius - robot_radius > 0).all(-1)


def test_plan_time_obstacle_reaches_the_checker_and_the_cost(planner):
    centre, radius = [0.0, 0.05], 0.25  # across every path the prior draws from START to GOAL (none avoids it)
    blocked = planner.plan(START, GOAL, n_samples=40, seed=0, obstacles=[mpd.Sphere(centre, radius)])
    ignored = planner.plan(START, GOAL, n_samples=40, seed=0)
    # the checker: plan.valid is the base scene's verdict and the new sphere's, computed independently
    base = CollisionChecker(load_task(TASK)).trajectories(
        torch.from_numpy(blocked.q), torch.from_numpy(blocked.dq), torch.from_numpy(blocked.ddq)
    )
    np.testing.assert_array_equal(blocked.valid, base.valid.numpy() & _sphere_free(blocked.q, centre, radius))
    # the cost: guided around the sphere, far more samples avoid it than when it is left out of the plan
    assert _sphere_free(ignored.q, centre, radius).mean() < 0.1 < 0.7 < _sphere_free(blocked.q, centre, radius).mean()
    assert blocked.provenance["obstacles"] == 1 and blocked.provenance["obstacles_digest"]


def test_plan_time_obstacles_equal_to_the_extra_objects_plan_like_the_extra_objects_scene():
    """The task's extra objects given as plan-time obstacles: the very same trajectories and verdicts as the task's
    extra-objects scene (the same grid, the same checker)."""
    task = load_task(TASK)
    obs = []
    for o in task.spec.environment.extra_objects:
        if o.type == "sphere":
            obs.append(mpd.Sphere(o.centre, o.radius))
        else:
            obs.append(mpd.Box(o.centre, np.asarray(o.size) / 2))
    given = mpd.load_planner(TASK, fast=False).plan(START, GOAL, n_samples=16, seed=1, obstacles=obs)
    scene = mpd.load_planner(TASK, fast=False, extra_objects=True).plan(START, GOAL, n_samples=16, seed=1)
    np.testing.assert_array_equal(given.q, scene.q)
    np.testing.assert_array_equal(given.valid, scene.valid)
    np.testing.assert_array_equal(given.cost, scene.cost)


def test_end_effector_goal_as_pose_matrix_or_configuration():
    from scipy.spatial.transform import Rotation

    from mpd.envs.primitives import quat_wxyz_to_matrix

    p = mpd.load_planner("EnvWarehouse-RobotPanda", fast=False)
    assert p.goal_kind == "pose"
    task = p.task
    qs = torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8], dtype=torch.float64)
    qg = torch.tensor([0.6, 0.1, 0.0, -1.9, 0.0, 2.0, 0.8], dtype=torch.float64)
    pos, rot = task.robot.ee_pose(qg)
    # the rotation as a quaternion (w, x, y, z) by scipy (an independent convention check), turned back
    x, y, z, w = Rotation.from_matrix(rot.numpy()).as_quat()
    quat = np.array([w, x, y, z])
    np.testing.assert_allclose(quat_wxyz_to_matrix(quat), rot.numpy(), atol=1e-9)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot.numpy(), pos.numpy()
    a = p.plan(qs, mpd.Pose(pos.numpy(), quat), n_samples=4, seed=0)
    b = p.plan(qs, T, n_samples=4, seed=0)
    c = p.plan(qs, qg, n_samples=4, seed=0)
    np.testing.assert_allclose(a.q, b.q, atol=1e-5)
    np.testing.assert_allclose(a.q, c.q, atol=1e-5)
    assert np.isfinite(a.metrics["ee_pos_error"]) or not a.valid.any()


@pytest.mark.parametrize(
    ("kwargs", "argument", "detail"),
    [
        ({"q_start": [float("nan"), 0.0]}, "q_start", "nan (not a finite number)"),
        ({"q_start": [0.0, 0.0, 0.0]}, "q_start", "expected 2"),
        ({"q_start": "abc"}, "q_start", "not an array of numbers"),
        ({"q_start": [1.5, 0.0]}, "q_start", "joint 0 = 1.5 is outside its limits"),
        ({"q_start": [-0.37, -0.12]}, "q_start", "in collision with the environment"),
        ({"goal": [0.5, float("inf")]}, "goal", "inf (not a finite number)"),
        ({"goal": mpd.Pose([0.1, 0.2, 0.3])}, "goal", "takes a joint configuration"),
        ({"goal": np.eye(4)}, "goal", "takes a joint configuration"),
        ({"goal": [0.5]}, "goal", "expected a joint configuration"),
        ({"obstacles": [mpd.Sphere([START[0], START[1]], 0.1)]}, "q_start", "in collision"),
        ({"obstacles": [mpd.Sphere([GOAL[0], GOAL[1]], 0.1)]}, "goal", "in collision"),
        ({"obstacles": [mpd.Sphere([0.0, 0.0, 0.0], 0.1)]}, "obstacles[0].center", "expected 2"),
        ({"obstacles": [mpd.Sphere([0.0, 0.0], 0.0)]}, "obstacles[0].radius", "must be positive"),
        ({"obstacles": [mpd.Box([0.0, 0.0], [0.1, -0.1])]}, "obstacles[0].half_extents", "must be positive"),
        ({"obstacles": [mpd.Box([0.0, 0.0], [0.1, 0.1], [[1, 1], [0, 1]])]}, "obstacles[0].rotation", "rotation"),
        ({"obstacles": [mpd.Sphere([0.0, 0.0], 0.1), (0.0, 0.0)]}, "obstacles[1]", "expected mpd.Sphere or mpd.Box"),
        ({"n_samples": 0}, "n_samples", "positive integer"),
        ({"n_samples": 2.5}, "n_samples", "positive integer"),
        ({"seed": -1}, "seed", "non-negative integer"),
    ],
)
def test_bad_input_fails_before_any_work_in_one_line_naming_the_argument(planner, kwargs, argument, detail):
    args = {"q_start": START, "goal": GOAL, **kwargs}
    calls = []
    orig = planner._planner.plan
    planner._planner.plan = lambda *a, **k: calls.append(1) or orig(*a, **k)
    try:
        with pytest.raises(mpd.PlanningInputError) as e:
            planner.plan(args.pop("q_start"), args.pop("goal"), **args)
    finally:
        planner._planner.plan = orig
    assert e.value.argument == argument and str(e.value).startswith(f"{argument}: ")
    assert detail in str(e.value) and "\n" not in str(e.value)
    assert not calls


def test_load_planner_bad_input():
    cases = [
        ({"task": "NoSuchTask"}, "task"),
        ({"method": "mpdd"}, "method"),
        ({"preset": "fast"}, "preset"),
        ({"guide_rate": 1.0}, "guide_rate"),
        ({"model": "not-an-identity"}, "model"),
    ]
    for kwargs, argument in cases:
        args = {"task": TASK, **kwargs}
        with pytest.raises(mpd.PlanningInputError) as e:
            mpd.load_planner(args.pop("task"), **args)
        assert e.value.argument == argument and "\n" not in str(e.value), str(e.value)


def test_every_method_plans_through_the_api():
    from mpd.planners import METHOD_ORDER

    for method in METHOD_ORDER:
        p = mpd.load_planner(TASK, method, fast=False, **({"rrt_time_limit": 0.5} if "rrt" in method else {}))
        r = p.plan(START, GOAL, n_samples=3, seed=0, obstacles=[mpd.Sphere([0.0, 0.05], 0.15)])
        assert r.q.shape[0] == 3 and r.provenance["method"] == method
        assert (r.provenance["model_identity"] is None) == (p.model is None)


class _ReachedPlanning(Exception):
    """Raised where the planner would start working: the input was accepted."""


# anything a caller might pass for an array argument: numbers of every kind, wrong shapes, strings, None, nested junk
_NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(-(10**20), 10**20),
    st.sampled_from([0.0, 0.5, -0.5, 1e-12, True]),
)
_JUNK = st.one_of(st.none(), st.text(max_size=3), st.just(object()), st.just({"a": 1}))
_VECTOR = st.one_of(
    st.lists(_NUMBER, min_size=0, max_size=8),
    st.lists(st.lists(_NUMBER, min_size=1, max_size=4), min_size=1, max_size=3),  # a matrix
    st.builds(lambda v: np.asarray(v, dtype=np.float64), st.lists(_NUMBER, min_size=1, max_size=8)),
    _JUNK,
)
_OBSTACLE = st.one_of(
    st.builds(mpd.Sphere, _VECTOR, st.one_of(_NUMBER, _JUNK)),
    st.builds(mpd.Box, _VECTOR, _VECTOR, st.one_of(st.none(), _VECTOR)),
    _JUNK,
    _VECTOR,
)


_VALID_OBSTACLES = st.lists(
    st.one_of(
        st.builds(mpd.Sphere, st.lists(st.floats(-0.9, 0.9), min_size=2, max_size=2), st.floats(0.01, 0.1)),
        st.builds(
            mpd.Box,
            st.lists(st.floats(-0.9, 0.9), min_size=2, max_size=2),
            st.lists(st.floats(0.01, 0.1), min_size=2, max_size=2),
        ),
    ),
    max_size=2,
)
_ARGUMENTS = ("q_start", "goal", "obstacles", "n_samples", "seed")
_BAD = {
    "q_start": _VECTOR,
    "goal": st.one_of(_VECTOR, st.builds(mpd.Pose, _VECTOR, _VECTOR), st.just(np.eye(4))),
    "obstacles": st.one_of(st.lists(_OBSTACLE, min_size=1, max_size=3), _JUNK, _NUMBER),
    "n_samples": st.one_of(st.integers(-3, 0), _NUMBER, _JUNK),
    "seed": st.one_of(st.integers(-3, -1), _NUMBER, _JUNK),
}


@given(data=st.data(), bad=st.sets(st.sampled_from(_ARGUMENTS), max_size=2))
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_any_input_is_planned_or_refused_in_one_line_naming_the_argument(planner, data, bad):
    """Hypothesis throws arbitrary values at every argument of ``plan``: each call either reaches the planner or raises
    PlanningInputError naming one of the arguments in one line, never another exception."""
    orig = planner._planner.plan

    def reached(*a, **k):
        raise _ReachedPlanning

    good = {"q_start": st.just(START), "goal": st.just(GOAL), "obstacles": st.one_of(st.none(), _VALID_OBSTACLES)}
    good |= {"n_samples": st.integers(1, 4), "seed": st.integers(0, 5)}
    args = {a: data.draw(_BAD[a] if a in bad else good[a], label=a) for a in _ARGUMENTS}
    given_args = dict(args)
    planner._planner.plan = reached
    try:
        planner.plan(args.pop("q_start"), args.pop("goal"), **args)
    except _ReachedPlanning:
        # accepted: then every argument is one a plan can use (a value drawn as "bad" may happen to be a good one)
        for name in ("q_start", "goal"):
            value = np.asarray(given_args[name], dtype=float)
            assert value.shape == (2,) and np.isfinite(value).all(), (name, given_args[name])
        for name, least in (("n_samples", 1), ("seed", 0)):
            value = given_args[name]
            assert isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= least, (
                name,
                value,
            )
    except mpd.PlanningInputError as e:
        msg = str(e)
        # the argument named is one drawn bad, or the start or goal put in collision by the obstacles
        blamable = bad | ({"q_start", "goal"} if given_args["obstacles"] else set())
        assert e.argument.split("[")[0].split(".")[0] in blamable, (msg, bad)
        assert msg.startswith(f"{e.argument}: ") and "\n" not in msg and "np.float64(" not in msg, msg
    finally:
        planner._planner.plan = orig
