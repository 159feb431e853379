"""Measurements behind the data-generation choices: sphere model vs PyBullet meshes, checker speeds.

``mpd data measure TASK`` prints them; the numbers quoted in ``datasets/README.md`` come from here.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from mpd.collision import CollisionChecker
from mpd.data.checkers import MeshChecker, SphereChecker
from mpd.envs.pybullet_scene import PyBulletScene
from mpd.tasks import Task


def _rates(sphere_free: np.ndarray, mesh_free: np.ndarray) -> dict[str, float]:
    """Agreement, and false free: the sphere model says free while the meshes collide (share of samples)."""
    return {
        "agree": float((sphere_free == mesh_free).mean()),
        "false_free": float((sphere_free & ~mesh_free).mean()),
        "false_coll": float((~sphere_free & mesh_free).mean()),
        "mesh_coll": float((~mesh_free).mean()),
        "sphere_coll": float((~sphere_free).mean()),
    }


def sphere_vs_mesh(task: Task, n: int = 10_000, seed: int = 0) -> dict[str, dict[str, float]]:
    """Sphere model (:class:`CollisionChecker`) against PyBullet on n random configurations, per scene.

    Environment: the sphere model with margin 0 and with the data clearance, against mesh contact (distance <=
    0) and against the meshes with the same clearance. Self collision, like with like: the sphere model's
    pairs against PyBullet on the same link pairs, and (for reference) against PyBullet on all non-adjacent
    pairs.
    """
    g = torch.Generator().manual_seed(seed)
    q = task.robot.random_q(n, g)
    qn = q.numpy()
    cl = task.spec.collision.clearance
    out: dict[str, dict[str, float]] = {}
    for extra in (False, True):
        tag = "extra" if extra else "train"
        env = task.env(extra)
        chk = CollisionChecker(task, extra, margin=0.0)
        d_env = chk.env_clearance(q).numpy()
        s_self = (chk.self_clearance(q) >= 0).numpy()
        with PyBulletScene(task.robot, env, self_pairs="sphere_pairs") as sc:
            dist = np.array([sc.min_env_distance(qi, max_distance=max(0.1, 2 * cl)) for qi in qn])
            m_self = np.array([sc.self_free(qi) for qi in qn]) if task.spec.collision.self_collision else None
        out[f"{tag}/env sphere(0) vs mesh(0)"] = _rates(d_env > 0, dist > 0)
        out[f"{tag}/env sphere({cl}) vs mesh(0)"] = _rates(d_env > cl, dist > 0)
        out[f"{tag}/env sphere({cl}) vs mesh({cl})"] = _rates(d_env > cl, dist > cl)
        if m_self is not None:
            out[f"{tag}/self sphere pairs vs mesh same pairs"] = _rates(s_self, m_self)
            if not extra:  # self collision does not depend on the scene
                with PyBulletScene(task.robot, None, self_pairs="all") as sc:
                    m_all = np.array([sc.self_free(qi) for qi in qn])
                out[f"{tag}/self sphere pairs vs mesh all non-adjacent pairs"] = _rates(s_self, m_all)
    return out


def _rate(fn, qs: np.ndarray, repeat: int = 1) -> float:
    fn(qs[:1])
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn(qs)
    return repeat * len(qs) / (time.perf_counter() - t0)


def checker_speeds(task: Task, n: int = 2000, seed: int = 0) -> dict[str, float]:
    """Checks per second (one thread): single configurations (how OMPL asks) and batches of 32 (an edge)."""
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(seed)
    q = task.robot.random_q(n, g).numpy()
    cl = task.spec.collision.clearance
    sph = SphereChecker(task, False, cl)
    mesh = MeshChecker(task, False, cl)
    ref = CollisionChecker(task, False, margin=cl)
    out = {
        "spheres numpy, single": _rate(lambda x: [sph.valid(qi[None]) for qi in x], q[:500]),
        "spheres numpy, batch 32": _rate(lambda x: [sph.valid(x[i : i + 32]) for i in range(0, len(x), 32)], q),
        "spheres torch CollisionChecker, single": _rate(
            lambda x: [ref.configs(torch.as_tensor(qi[None])) for qi in x], q[:200]
        ),
        "spheres torch CollisionChecker, batch 32": _rate(
            lambda x: [ref.configs(torch.as_tensor(x[i : i + 32])) for i in range(0, len(x), 32)], q
        ),
        "pybullet meshes, single": _rate(mesh.valid, q),
    }
    e1, s1 = sph.check(q)
    e2, s2 = mesh.check(q)
    out["agreement env (both with clearance)"] = float((e1 == e2).mean())
    out["agreement self (like with like)"] = float((s1 == s2).mean())
    out["agreement valid"] = float(((e1 & s1) == (e2 & s2)).mean())
    mesh.close()
    return out


def planning_speed(task: Task, n: int = 20, seed: int = 0) -> dict[str, dict[str, float]]:
    """RRTConnect + simplifyMax + resampling with each checker on the same n problems (start and goal valid
    for both checkers): CPU seconds per problem (robust to other processes on the machine) and successes."""
    from mpd.data.checkers import make_checker
    from mpd.data.contexts import ContextSampler
    from mpd.data.planning import JointSpacePlanner, PlannerSettings, default_check_step

    torch.set_num_threads(1)
    cl = task.spec.collision.clearance
    checkers = {k: make_checker(task, k, cl) for k in ("spheres", "meshes")}

    class Both:  # valid for both checkers
        def valid(self, q):
            return checkers["spheres"].valid(q) & checkers["meshes"].valid(q)

    sampler = ContextSampler(task, Both())
    problems = [sampler.sample(np.random.default_rng([seed, i])) for i in range(n)]
    settings = PlannerSettings(time_limit=task.spec.data.planner_time_limit, check_step=default_check_step(task))
    out = {}
    for kind, chk in checkers.items():
        planner = JointSpacePlanner(chk, settings, task.spec.trajectory.n_points)
        t0, c0 = time.perf_counter(), time.process_time()
        ok = sum(planner.plan(p.q_start, p.q_goal, i + 1).success for i, p in enumerate(problems))
        out[kind] = {
            "cpu_s_per_problem": (time.process_time() - c0) / n,
            "wall_s_per_problem": (time.perf_counter() - t0) / n,
            "successes": ok,
        }
        chk.close()
    return out
