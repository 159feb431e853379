"""Motion-planning costs: analytic gradients against autograd references, the composite's rules, the EE cost.

Each autograd reference rebuilds a cost from differentiable pieces that share no code with ``mpd.costs``: the
dense trajectory, ``Robot.kinematics`` (autograd runs through it), the analytic SDF ``Environment.sdf``, and
an SE(3) log written here with acos / V^-1 formulas. Inputs are random (seeded) trajectories that put every
cost term to work; ReLU boundaries, max-pair switches and SDF kinks have measure zero, so random inputs avoid
them.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from mpd import kernels
from mpd.costs import COSTS, CostFunction, CostInput
from mpd.costs.base import spheres_vjp_sparse
from mpd.costs.ee_pose import ee_pose_error
from mpd.costs.sdf import sdf_batch_last
from mpd.costs.se3 import se3_half_sq_log_grad, se3_log, so3_log
from mpd.envs import Environment
from mpd.tasks import load_task
from mpd.tasks.task import Task
from mpd.trajectory import make_parametrization

F64 = torch.float64
TOL = 1e-6  # relative error of a gradient (float64)

# (task, extra objects, number of trajectories)
CASES = {
    "pointmass": ("EnvSimple2D-RobotPointMass2D", True, 3),
    "planar4": ("EnvPlanar4Link-RobotPlanar4Link", False, 3),
    "panda_spheres": ("EnvSpheres3D-RobotPanda", True, 2),
    "panda_warehouse": ("EnvWarehouse-RobotPanda", False, 2),
}


# ----------------------------------------------------------------------------------------------- references
def _hat(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(w[..., 0])
    rows = [[z, -w[..., 2], w[..., 1]], [w[..., 2], z, -w[..., 0]], [-w[..., 1], w[..., 0], z]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def ref_so3_log(R: torch.Tensor) -> torch.Tensor:
    """Textbook log (away from 0 and pi): theta = acos((tr R - 1)/2), phi = theta vee(R - R^T) / (2 sin)."""
    theta = torch.acos(((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    A = R - R.transpose(-1, -2)
    w = torch.stack([A[..., 2, 1], A[..., 0, 2], A[..., 1, 0]], -1) / 2
    return (theta / torch.sin(theta))[..., None] * w


def ref_se3_log(T: torch.Tensor) -> torch.Tensor:
    """[rho; phi] of 4x4 poses: rho = V^-1 t, V^-1 = I - A/2 + (1 - th sin th / (2 (1 - cos th))) A^2/th^2."""
    phi = ref_so3_log(T[..., :3, :3])
    th = phi.norm(dim=-1)[..., None, None]
    A = _hat(phi)
    Vinv = torch.eye(3, dtype=T.dtype) - A / 2 + (1 - th * torch.sin(th) / (2 * (1 - torch.cos(th)))) / th**2 * A @ A
    return torch.cat([(Vinv @ T[..., :3, 3:])[..., 0], phi], -1)


def _pose(p: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    T = torch.zeros(*p.shape[:-1], 4, 4, dtype=p.dtype)
    T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = R, p, 1
    return T


def reference(task, param, env, preset: str, name: str, free, q_start, q_goal, ee_goal) -> torch.Tensor:
    """Cost (B,) of one term, written independently with differentiable torch ops."""
    d = param.dense(free, q_start, q_goal)
    B, n, dof = d.q.shape
    r = task.robot
    w = torch.full((n,), d.duration / (n - 1), dtype=F64)
    if preset == "official":
        w[0] = w[-1] = w[0] / 2
    integral = lambda c: (c * w).sum(-1)  # noqa: E731
    if name in ("velocity", "acceleration"):
        sq = (d.dq_ds if name == "velocity" else d.ddq_ds2).pow(2).sum(-1)
        return integral(0.5 * sq if preset == "paper" else 0.5 * torch.sqrt(sq + 1e-12))
    if name == "joint_limits":
        e, T = 0.03, d.duration
        terms = [(d.q, r.q_min + e, r.q_max - e)]
        if r.dq_max is not None:
            terms.append((d.dq_ds, -(r.dq_max - e) * T, (r.dq_max - e) * T))  # margin in rad/s, then to phase
        if r.ddq_max is not None:
            terms.append((d.ddq_ds2, -(r.ddq_max - e) * T**2, (r.ddq_max - e) * T**2))
        c = sum(0.5 * (torch.relu(x - hi) + torch.relu(lo - x)).pow(2).sum(-1) for x, lo, hi in terms)
        return integral(c)
    if name in ("collision", "self_collision"):
        centres = r.kinematics(d.q.reshape(-1, dof)).points.reshape(B, n, -1, 3)
        if name == "collision":
            sdf = env.sdf(centres[..., : task.dim], mode="analytic")
            pen = r.sphere_radii + task.spec.collision.cost_margin - sdf
            return integral(torch.relu(pen).sum(-1))
        eps = 0.0 if preset == "official" else task.spec.collision.cost_margin
        i, j = r.self_pairs[:, 0], r.self_pairs[:, 1]
        dist = (centres[..., i, :] - centres[..., j, :]).norm(dim=-1)
        pen = r.sphere_radii[i] + r.sphere_radii[j] + eps - dist
        return integral(torch.relu(pen.max(-1).values))
    assert name == "ee_pose"
    kin = r.kinematics(d.q[:, -1])
    gp, gR = ee_goal
    if preset == "official":
        Rt = kin.ee_rot.transpose(-1, -2)  # T^-1 = (R^T, -R^T p)
        xi = ref_se3_log(_pose(gp, gR) @ _pose(-(Rt @ kin.ee_pos[..., None])[..., 0], Rt))
        return 0.5 * xi.pow(2).sum(-1)
    phi = ref_so3_log(gR.transpose(-1, -2) @ kin.ee_rot)
    return 0.5 * (gp - kin.ee_pos).pow(2).sum(-1) + 0.5 * phi.pow(2).sum(-1)


def analytic(task, param, env, preset, name, free, q_start, q_goal, ee_goal, sdf_mode="analytic"):
    """Value (B,) and gradient w.r.t. the free rows of one cost of mpd.costs (no composite rules)."""
    cost = COSTS[name](task, preset)
    term = cost(CostInput(param.dense(free, q_start, q_goal), task, env, ee_goal, sdf_mode), 1.0)
    return term.value, param.grad_to_free(term.g_q, term.g_dq, term.g_ddq)


# ----------------------------------------------------------------------------------------------- inputs
def _make_case(key: str, kind: str):
    """Task, parametrization, env and a seeded float64 batch in which every cost term is active."""
    name, extra, B = CASES[key]
    from mpd.tasks import load_task

    task = load_task(name)
    param = make_parametrization(task, kind)
    env = task.env(extra_objects=extra)
    r = task.robot
    g = torch.Generator().manual_seed(7)
    q_start, q_end = r.random_q(B, g), r.random_q(B, g)
    s = torch.linspace(0, 1, param.n_free, dtype=F64)[None, :, None]
    free = (
        q_start[:, None] * (1 - s)
        + q_end[:, None] * s
        + 0.3 * torch.randn(B, param.n_free, r.dof, generator=g, dtype=F64)
    )
    # position, velocity and acceleration limit violations: a zig-zag on the first joint, rows past q_max
    free[0, 2:-2, 0] += 0.6 * (-1.0) ** torch.arange(param.n_free - 4)
    free[1, param.n_free // 2 - 2 : param.n_free // 2 + 2] = r.q_max + 0.2
    if len(r.self_pairs):
        # a deep self collision in the middle of trajectory 0
        cand = r.random_q(4000, g)
        depth = -r.self_collision_distance(r.sphere_centres(cand)).min(-1).values
        free[0, param.n_free // 2 - 2 : param.n_free // 2 + 2] = cand[depth.argmax()]
    q_goal = None if task.ee_goal else q_end
    ee_goal = None
    if task.ee_goal:
        # goal = the final pose turned by 0.5-2.5 rad and moved 0.1-0.3 m: away from the logs' singularities
        q1 = param.dense(free, q_start).q[:, -1]
        p1, R1 = r.ee_pose(q1)
        axis = torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=F64), dim=-1)
        ang = 0.5 + 2 * torch.rand(B, 1, generator=g, dtype=F64)
        Rg = torch.linalg.matrix_exp(_hat(axis * ang)) @ R1
        pg = p1 + 0.1 + 0.2 * torch.rand(B, 3, generator=g, dtype=F64)
        ee_goal = (pg, Rg)
    return task, param, env, free, q_start, q_goal, ee_goal


_CASES: dict = {}


def case(key: str, kind: str):
    if (key, kind) not in _CASES:
        _CASES[key, kind] = _make_case(key, kind)
    return _CASES[key, kind]


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


# ----------------------------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("kind", ["bspline", "waypoints"])
@pytest.mark.parametrize("preset", ["official", "paper"])
@pytest.mark.parametrize("key", list(CASES))
def test_gradients_match_autograd(key, preset, kind):
    task, param, env, free, q_start, q_goal, ee_goal = case(key, kind)
    names = [n for n, cls in COSTS.items() if cls.applicable(task)]
    expected = {"pointmass": 4, "planar4": 6, "panda_spheres": 6, "panda_warehouse": 6}[key]
    assert len(names) == expected
    for name in names:
        x = free.clone().requires_grad_(True)
        ref = reference(task, param, env, preset, name, x, q_start, q_goal, ee_goal)
        (g_ref,) = torch.autograd.grad(ref.sum(), x)
        value, grad = analytic(task, param, env, preset, name, free, q_start, q_goal, ee_goal)
        assert float(ref.detach().sum()) > 0, f"{name}: an inactive term tests nothing"
        assert g_ref.norm() > 0, f"{name}: zero reference gradient"
        # 1e-7: the Panda's fixed URDF rotations are orthonormal to 3e-8 only (parsed in float32), and the two
        # SO(3) logs (atan2 here, acos in the reference) react differently to that
        torch.testing.assert_close(value, ref.detach(), rtol=1e-7, atol=1e-12, msg=f"{name} value")
        assert _rel(grad, g_ref) <= TOL, (
            f"{key}/{preset}/{kind}/{name}: relative gradient error {_rel(grad, g_ref):.2e}"
        )


def test_panda_composite_vs_finite_differences():
    task, param, env, free, q_start, _, ee_goal = case("panda_spheres", "bspline")
    cf = CostFunction(task, param, env, preset="paper", sdf_mode="analytic")
    res = cf(free, q_start, None, ee_goal)
    g = torch.Generator().manual_seed(1)
    h = 1e-6
    for _ in range(3):
        v = torch.randn(free.shape, generator=g, dtype=F64)
        fd = (cf(free + h * v, q_start, None, ee_goal).total - cf(free - h * v, q_start, None, ee_goal).total) / (2 * h)
        torch.testing.assert_close((res.grad * v).sum((1, 2)), fd, rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------------------------- composite
@pytest.mark.parametrize("kind", ["bspline", "waypoints"])
@pytest.mark.parametrize("preset", ["official", "paper"])
def test_composite_weighted_sum_and_ee_rule(preset, kind):
    task, param, env, free, q_start, q_goal, ee_goal = case("panda_spheres", kind)
    cf = CostFunction(task, param, env, preset=preset, sdf_mode="analytic", profile=True)
    res = cf(free, q_start, q_goal, ee_goal)
    weights = task.cost_weights(preset)
    assert set(res.values) == set(COSTS)
    total = sum(getattr(weights, k) * v for k, v in res.values.items())
    torch.testing.assert_close(res.total, total, rtol=1e-12, atol=0)
    grads = {}
    for name in res.values:
        _, grads[name] = analytic(task, param, env, preset, name, free, q_start, q_goal, ee_goal)
    others = sum(getattr(weights, k) * g for k, g in grads.items() if k != "ee_pose")
    ee = weights.ee_pose * grads["ee_pose"]
    if preset == "official":
        # the authors' rule: the final configuration (last free row) follows the EE cost only
        torch.testing.assert_close(res.grad[:, :-1], others[:, :-1], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(res.grad[:, -1], ee[:, -1], rtol=1e-10, atol=1e-10)
        assert ee[:, :-1].abs().max() == 0  # q(1) depends on the last free row only
    else:
        torch.testing.assert_close(res.grad, others + ee, rtol=1e-10, atol=1e-10)
    # velocity, acceleration and joint limits run in one compiled pass, timed as "phase"
    fused = {"velocity", "acceleration", "joint_limits"}
    assert {"dense", "fk", "chain_rule", "phase", *(set(res.values) - fused)} == set(res.timings)
    assert all(t >= 0 for t in res.timings.values())


def test_skipped_costs():
    pm = load_task("EnvSimple2D-RobotPointMass2D")
    param = make_parametrization(pm, "bspline")
    for preset in ("official", "paper"):
        cf = CostFunction(pm, param, pm.env(), preset=preset)
        assert set(cf.names) == {
            "velocity",
            "acceleration",
            "joint_limits",
            "collision",
        }  # no EE, no self pairs
    cf = CostFunction(pm, param, pm.env(), weights={"velocity": 0.0, "acceleration": 0})
    assert set(cf.names) == {"joint_limits", "collision"}
    # the point mass has no velocity / acceleration limits: the joint-limit cost has no q', q'' terms
    B = 2
    q = torch.zeros(B, 2, dtype=F64)
    inp = CostInput(param.dense(torch.zeros(B, param.n_free, 2, dtype=F64), q, q), pm, pm.env())
    term = COSTS["joint_limits"](pm, "official")(inp)
    assert term.g_dq is None and term.g_ddq is None
    # self collision switched off in the task file
    p4 = load_task("EnvPlanar4Link-RobotPlanar4Link")
    spec = dataclasses.replace(p4.spec, collision=dataclasses.replace(p4.spec.collision, self_collision=False))
    p4_off = Task(spec, p4.path)
    assert "self_collision" not in CostFunction(p4_off, make_parametrization(p4_off), p4_off.env()).names
    assert "self_collision" in CostFunction(p4, make_parametrization(p4), p4.env()).names
    with pytest.raises(ValueError, match="unknown cost names"):
        CostFunction(pm, param, pm.env(), weights={"smoothness": 1.0})
    with pytest.raises(ValueError, match="ee_goal"):
        CostFunction(p4, make_parametrization(p4), p4.env())(
            torch.zeros(1, make_parametrization(p4).n_free, 4), torch.zeros(1, 4)
        )


@pytest.mark.parametrize("key", ["pointmass", "planar4", "panda_spheres"])
def test_nearest_sdf_matches_grid_and_gradient_direction(key):
    task, param, env, free, q_start, q_goal, ee_goal = case(key, "bspline")
    if task.dim == 3:  # a coarser grid of the same scene (fixed + extra objects): the 2 cm one takes ~10 s to build
        env = Environment(dataclasses.replace(env.spec, sdf_cell_size=0.05), extra_objects=True)
    kin = task.robot.kinematics(param.dense(free, q_start, q_goal).q.reshape(-1, task.dof))
    X = kin.points_t[:, : task.dim].float()
    d, g = sdf_batch_last(env, X, "nearest")
    d_ref, g_ref = env.sdf(X.permute(2, 0, 1), grad=True, mode="nearest")
    assert torch.equal(d, d_ref.t()) and torch.equal(g, g_ref.permute(1, 2, 0))
    # outside the grid box the distance to the box is added, as GridSDF.query does
    far = X + 10.0
    assert torch.equal(sdf_batch_last(env, far, "nearest")[0], env.sdf(far.permute(2, 0, 1), mode="nearest").t())
    # the nearest-node gradient points the way of the exact one (these trajectories run deep into obstacles)
    _, g_near = analytic(task, param, env, "official", "collision", free, q_start, q_goal, ee_goal, "nearest")
    _, g_exact = analytic(task, param, env, "official", "collision", free, q_start, q_goal, ee_goal, "analytic")
    cos = torch.nn.functional.cosine_similarity(g_near.flatten(1), g_exact.flatten(1), dim=1)
    assert (cos > 0.9).all(), cos


@pytest.mark.parametrize("key", list(CASES))
def test_sparse_and_dense_jacobian_products_agree(key, monkeypatch):
    """The collision cost's two Jacobian products (dense over all spheres, sparse over active entries)."""
    import mpd.costs.collision as collision

    task, param, env, free, q_start, q_goal, ee_goal = case(key, "bspline")
    out = {}
    for frac in (0.0, 1.0):
        monkeypatch.setattr(collision, "SPARSE_FRACTION", frac)
        out[frac] = analytic(task, param, env, "official", "collision", free, q_start, q_goal, ee_goal)[1]
    torch.testing.assert_close(out[0.0], out[1.0], rtol=1e-12, atol=1e-12)
    # and spheres_vjp_sparse on arbitrary entries, root-link spheres included (the point mass has only those)
    r = task.robot
    kin = r.kinematics(r.random_q(40, torch.Generator().manual_seed(2)))
    g = torch.Generator().manual_seed(3)
    mask = torch.rand(r.n_spheres, 40, generator=g) < 0.3
    G = torch.randn(r.n_spheres, 3, 40, generator=g, dtype=F64) * mask[:, None]
    if task.dim == 2:
        G[:, 2] = 0
    flat = mask.reshape(-1).nonzero().squeeze(1)
    sparse = spheres_vjp_sparse(r, kin, flat, G.permute(0, 2, 1).reshape(-1, 3)[flat, : task.dim], 40)
    torch.testing.assert_close(sparse, r.spheres_vjp(kin, G.permute(2, 0, 1)), rtol=1e-12, atol=1e-12)


def test_self_collision_culling_is_exact():
    """The cluster test never drops an active pair: the same max as over all pairs, on configurations close to
    contact (float32, the planner's dtype)."""
    from mpd.costs.self_collision import SelfCollisionCost

    for name in ("EnvSpheres3D-RobotPanda", "EnvPlanar4Link-RobotPlanar4Link"):
        task = load_task(name)
        r = task.robot
        q = r.random_q(20000, torch.Generator().manual_seed(11), dtype=torch.float32)
        kin = r.kinematics(q)
        cost = SelfCollisionCost(task, "official")
        pen_all = (-r.self_collision_distance(kin.points)).max(-1).values
        cand = cost.candidates(kin.points_t)
        assert cand.numel() < 0.25 * len(q)  # the test culls something
        pen_cand = torch.full_like(pen_all, -1.0)
        pen_cand[cand] = cost.deepest_pair(kin.points_t[cost._used].index_select(2, cand))[0]
        hit = pen_all > 0
        assert hit.sum() > 100
        torch.testing.assert_close(pen_cand[hit], pen_all[hit], rtol=0, atol=1e-6)
        assert (pen_cand[~hit] <= 0).all()


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("preset", ["official", "paper"])
def test_compiled_self_collision_is_the_torch_path(dtype, preset):
    """The compiled self-collision pass (``mpd.costs.self_collision_kernel``) against the torch path: the same
    penetration per configuration, the same deepest pairs, so the same cost and gradient; and against the
    maximum over all pairs without any culling (``Robot.self_collision_distance``)."""
    from mpd.costs import self_collision_kernel
    from mpd.costs.self_collision import SelfCollisionCost

    for name in ("EnvSpheres3D-RobotPanda", "EnvPlanar4Link-RobotPlanar4Link"):
        task = load_task(name)
        r = task.robot
        param = make_parametrization(task, "bspline")
        cost = SelfCollisionCost(task, preset)
        args = self_collision_kernel.kernel_args(
            cost._levels, cost.blocks, cost._used, r.sphere_radii.numpy(), cost.margin, dtype
        )
        # random configurations: 1-2 % in self collision
        kin = r.kinematics(r.random_q(20000, torch.Generator().manual_seed(12), dtype=dtype))
        pen, config, i, j, _ = self_collision_kernel.self_pass(kin.points_t, args)
        pen_all = (cost.margin - r.self_collision_distance(kin.points)).max(-1)
        hit = pen_all.values > 0
        assert hit.sum() > 100, "the configurations test nothing"
        assert torch.equal(config, hit.nonzero().squeeze(1))
        tol = 1e-6 if dtype == torch.float32 else 1e-12
        torch.testing.assert_close(pen[hit], pen_all.values[hit], rtol=0, atol=tol)
        assert (pen[~hit] == 0).all()
        d_ij = (kin.points_t[i, :, config] - kin.points_t[j, :, config]).norm(dim=-1)
        rad = r.sphere_radii.to(dtype)
        torch.testing.assert_close(rad[i] + rad[j] + cost.margin - d_ij, pen[config], rtol=0, atol=tol)
        # the cost through both paths, on trajectories through random configurations
        q = r.random_q(20 * param.n_free + 40, torch.Generator().manual_seed(13), dtype=dtype)
        free = q[: 20 * param.n_free].view(20, param.n_free, -1)
        dense = param.dense(free, q[-40:-20], None if task.ee_goal else q[-20:])
        terms = {}
        for compiled in (True, False):
            c = SelfCollisionCost(task, preset)
            with kernels.use("compiled" if compiled else "torch", "self_collision"):
                terms[compiled] = c(CostInput(dense, task, task.env(), None, "nearest"), 2.0)
        assert (terms[False].value > 0).any()
        # a trajectory's value sums its 128 configurations' terms in another order than torch's reduction (whose
        # kernels differ by CPU: AVX2 vs AVX-512), so in float32 the two agree to the sum's rounding (~n eps), not
        # to one term's (measured on an AVX2 EPYC: 2.1e-6 relative)
        sum_tol = 2e-5 if dtype == torch.float32 else tol
        torch.testing.assert_close(terms[True].value, terms[False].value, rtol=sum_tol, atol=0)
        torch.testing.assert_close(terms[True].g_q, terms[False].g_q, rtol=tol, atol=tol)


# ----------------------------------------------------------------------------------------------- EE pose
def test_ee_cost_zero_at_goal():
    g = torch.Generator().manual_seed(3)
    R = torch.linalg.matrix_exp(_hat(torch.randn(5, 3, generator=g, dtype=F64)))
    p = torch.randn(5, 3, generator=g, dtype=F64)
    for preset in ("official", "paper"):
        value, g_pos, g_rot = ee_pose_error(preset, p, R, p.clone(), R.clone())
        assert value.abs().max() < 1e-28 and g_pos.abs().max() < 1e-14 and g_rot.abs().max() < 1e-14
    # through the robot: the goal is the final pose of the trajectories (the Panda's URDF rotations are
    # orthonormal to 3e-8 only, hence the looser bound)
    task = load_task("EnvSpheres3D-RobotPanda")
    param = make_parametrization(task, "bspline")
    free = task.robot.random_q(5 * param.n_free, g).reshape(5, param.n_free, task.dof)
    q_start = task.robot.random_q(5, g)
    goal = task.robot.ee_pose(param.dense(free, q_start).q[:, -1])
    for preset in ("official", "paper"):
        value, grad = analytic(task, param, task.env(), preset, "ee_pose", free, q_start, None, goal)
        assert value.abs().max() < 1e-14 and grad.abs().max() < 1e-6


def test_ee_forms_agree_for_small_motions_near_origin():
    g = torch.Generator().manual_seed(4)
    R = torch.linalg.matrix_exp(_hat(torch.randn(4, 3, generator=g, dtype=F64)))
    p = torch.zeros(4, 3, dtype=F64)
    for v_scale, w_scale, rtol in ((1e-3, 1e-3, 2e-3), (0.5, 0.0, 1e-12), (0.0, 0.5, 1e-12)):
        v = v_scale * torch.randn(4, 3, generator=g, dtype=F64)
        w = w_scale * torch.randn(4, 3, generator=g, dtype=F64)
        M = torch.zeros(4, 4, 4, dtype=F64)
        M[:, :3, :3], M[:, :3, 3] = _hat(w), v
        goal = torch.linalg.matrix_exp(M) @ _pose(p, R)  # T_goal = exp(xi) T_ee, so log(T_goal T_ee^-1) = xi
        official, _, _ = ee_pose_error("official", p, R, goal[:, :3, 3], goal[:, :3, :3])
        paper, _, _ = ee_pose_error("paper", p, R, goal[:, :3, 3], goal[:, :3, :3])
        torch.testing.assert_close(official, 0.5 * (v.pow(2).sum(-1) + w.pow(2).sum(-1)), rtol=1e-10, atol=0)
        torch.testing.assert_close(paper, official, rtol=rtol, atol=0)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("preset", ["official", "paper"])
def test_compiled_ee_cost_is_the_torch_path(dtype, preset):
    """The compiled end-effector pass (``mpd.costs.ee_kernel``) against the torch path (``ee_pose_error``,
    ``Robot.ee_vjp``): values and gradients for goals at the final pose, rotated from it by angles below and above
    the series' switch, near pi (the axis from the symmetric part) and anywhere, with the final configurations' frames
    taken from the FK of all configurations and from an FK of their own."""
    from mpd.costs.ee_pose import EEPoseCost

    task = load_task("EnvSpheres3D-RobotPanda")
    r, param = task.robot, make_parametrization(task, "bspline")
    g = torch.Generator().manual_seed(21)
    B = 48
    free = r.random_q(B * param.n_free, g, F64).reshape(B, param.n_free, task.dof)
    q_start = r.random_q(B, g, F64)
    dense = param.dense(free.to(dtype), q_start.to(dtype))
    p_ee, R_ee = r.ee_pose(dense.q[:, -1].double())
    # rotations of the goal about random axes: 0, tiny, below and above the float32 switch (0.5), up to 3e-6 from pi
    # (at pi itself the axis's sign is a choice that rounding makes: the two paths may choose differently)
    axis = torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=F64), dim=-1)
    ang = torch.tensor([0.0, 1e-6, 0.02, 0.3, 0.49, 0.51, 1.5, 2.7, 2.9, 3.1, 3.13, 3.14159], dtype=F64)
    ang = ang.repeat(B // len(ang))
    R_goal = torch.linalg.matrix_exp(_hat(axis * ang[:, None])) @ R_ee
    p_goal = p_ee + 0.3 * torch.randn(B, 3, generator=g, dtype=F64) * (ang[:, None] > 0.1)
    p_goal[-6:], R_goal[-6:] = r.ee_pose(r.random_q(6, g, F64))  # anywhere
    assert (torch.diagonal(R_goal.transpose(1, 2) @ R_ee, dim1=1, dim2=2).sum(-1) < -0.8).sum() >= 8  # near pi
    goal = (p_goal.to(dtype), R_goal.to(dtype))
    # the pass's own logarithm and V^-1 coefficients (float64 arithmetic, the dtype's switch to the series) against
    # se3's in float64, one angle at a time: they differ by the series' truncation (~1e-6 relative at 0.5), while
    # the cost's tolerance below is the float32 path's rounding (whose closed forms cancel: 3e-4 at 0.5)
    from mpd.costs import ee_kernel, se3

    small = se3.series_below(dtype)
    rot = torch.linalg.matrix_exp(_hat(axis * ang[:, None]))
    for k in range(len(ang)):
        c, dc = ee_kernel._vinv_coeffs(float(ang[k]), small)
        c_ref, dc_ref = se3._vinv_coeffs(ang[k : k + 1])
        torch.testing.assert_close(torch.tensor([c, dc], dtype=F64), torch.cat([c_ref, dc_ref]), rtol=5e-6, atol=0)
        phi, _ = ee_kernel._so3_log(rot[k].numpy(), small)
        torch.testing.assert_close(torch.from_numpy(phi), se3.so3_log(rot[k])[0], rtol=2e-6, atol=1e-9)
    tol = dict(rtol=2e-4, atol=2e-4) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-10)
    for with_fk in (True, False):
        out = {}
        for compiled in (True, False):
            cost = EEPoseCost(task, preset)
            inp = CostInput(dense, task, task.env(), goal, "nearest")
            if with_fk:
                inp.kinematics()
            with kernels.use("compiled" if compiled else "torch", "ee_pose"):
                out[compiled] = cost(inp, 1.7)
        assert out[False].value.max() > 1
        torch.testing.assert_close(out[True].value, out[False].value, **tol)
        torch.testing.assert_close(out[True].g_q, out[False].g_q, **tol)
        assert out[True].g_q[:, :-1].abs().max() == 0 and (out[True].g_q[:, -1] != 0).any(-1).sum() >= B - 4


def test_se3_log_and_gradient():
    """The log inverts exp at all angles (0, tiny, pi); the gradient of 1/2|log|^2 is exact, and the authors'
    -J^T xi (i.e. xi itself as the gradient) is only its first-order approximation."""
    g = torch.Generator().manual_seed(5)
    axis = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=F64), dim=-1)
    ang = torch.tensor([0.0, 1e-9, 1e-3, 1.0, 3.14159, torch.pi], dtype=F64)[:, None]
    R = torch.linalg.matrix_exp(_hat(axis * ang))
    phi, theta = so3_log(R)
    torch.testing.assert_close(torch.linalg.matrix_exp(_hat(phi)), R, rtol=0, atol=1e-12)
    torch.testing.assert_close(theta, ang[:, 0], rtol=0, atol=1e-12)
    # gradient of f(eps) = 1/2 |log(E exp(eps))|^2 by autograd through the reference log
    xi0 = torch.randn(8, 6, generator=g, dtype=F64)
    M = torch.zeros(8, 4, 4, dtype=F64)
    M[:, :3, :3], M[:, :3, 3] = _hat(xi0[:, 3:]), xi0[:, :3]
    E = torch.linalg.matrix_exp(M)
    xi, parts = se3_log(E[:, :3, :3], E[:, :3, 3])
    torch.testing.assert_close(xi, ref_se3_log(E), rtol=1e-10, atol=1e-12)
    eps = torch.zeros(8, 6, dtype=F64, requires_grad=True)
    Me = torch.zeros(8, 4, 4, dtype=F64)
    Me[:, :3, :3], Me[:, :3, 3] = _hat(eps[:, 3:]), eps[:, :3]
    f = 0.5 * ref_se3_log(E @ torch.linalg.matrix_exp(Me)).pow(2).sum()
    (auto,) = torch.autograd.grad(f, eps)
    grad = se3_half_sq_log_grad(parts)
    assert _rel(grad, auto) < 1e-9
    assert _rel(xi, auto) > 1e-2  # -J^T xi is not the gradient for finite errors


@pytest.mark.parametrize("key", list(CASES))
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_compiled_collision_pass_is_the_torch_path(key, dtype):
    """The compiled CPU pass of the collision cost (``mpd.costs.collision_kernel``) against the torch lines it
    replaces: the same nearest nodes (so equal distances and gradients), the same active entries, the same cost,
    for sphere centres inside the grid box, exactly half-way between nodes (rounding ties), on and beyond the box's
    faces (clamped, the distance to the box added), with the extra objects where the task has them."""
    from mpd.costs import collision_kernel
    from mpd.costs.collision import CollisionCost

    task, param, env, free, q_start, q_goal, ee_goal = case(key, "bspline")
    dense = param.dense(free.to(dtype), q_start.to(dtype), None if q_goal is None else q_goal.to(dtype))
    inp = CostInput(dense, task, env, ee_goal, "nearest")
    X = inp.kinematics().points_t.clone()
    S, _, N = X.shape
    D = task.dim
    grid = env.grid("fixed")
    lo, hi = (torch.as_tensor(v, dtype=dtype) for v in (grid.lo, grid.hi))
    g = torch.Generator().manual_seed(5)
    cols = torch.randperm(N, generator=g)[: N // 2]
    # half of the columns: ties (node + cell / 2), points on the faces and up to 0.3 m beyond them
    k = torch.randint(0, min(grid.shape) - 1, (S, D, len(cols)), generator=g)
    ties = lo.view(1, D, 1) + (k.to(dtype) + 0.5) * grid.cell
    X[:, :D, cols[: len(cols) // 2]] = ties[..., : len(cols) // 2]
    u = torch.rand(S, D, len(cols) - len(cols) // 2, generator=g, dtype=dtype)
    X[:, :D, cols[len(cols) // 2 :]] = lo.view(1, D, 1) - 0.3 + (hi - lo + 0.6).view(1, D, 1) * u
    X[:, :D, cols[len(cols) // 2 :: 7]] = hi.view(1, D, 1).to(dtype)  # exactly on the upper faces
    radius = (task.robot.sphere_radii + 0.05).to(X)[:, None]
    w = torch.rand(dense.q.shape[1], generator=g, dtype=dtype)
    chain = task.robot.chain
    frames = (chain.point_joint + 1, chain.dof)
    value, flat, rows, _ = collision_kernel.collision_pass(env, X, radius, w, 3.0, reach=None, frames=frames)
    # the torch path (CollisionCost's reference lines)
    d, gd = sdf_batch_last(env, X[:, :D], "nearest")
    a = radius - d
    relu = a.clamp_min(0)
    wN = w.repeat(N // len(w))
    assert torch.equal(flat, (relu > 0).reshape(-1).nonzero().squeeze(1))
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(value, (relu * wN).sum(0), rtol=tol, atol=0)
    ref_G = torch.zeros(S, 3, N, dtype=dtype)
    ref_G[:, :D] = (relu > 0)[:, None] * (-3.0 * wN) * gd
    G = torch.zeros_like(ref_G)
    G[flat // N, :, flat % N] = rows
    torch.testing.assert_close(G, ref_G, rtol=tol, atol=0)
    # the frames' sums accumulated in the pass (gradients, their moments about the origin from the centres) give
    # the Jacobian product of the (S, 3, N) gradient, on the robot's own centres
    kin = inp.kinematics()
    _, flat0, rows0, H = collision_kernel.collision_pass(env, kin.points_t, radius, w, 3.0, reach=None, frames=frames)
    assert flat0.numel() > 0
    G0 = torch.zeros(S, 3, N, dtype=dtype)
    G0[flat0 // N, :, flat0 % N] = rows0
    ref_q = chain.points_vjp_frames(kin, G0)
    got_q = chain.vjp_from_forces(kin, H[:, 0], H[:, 1])
    torch.testing.assert_close(got_q, ref_q, rtol=tol * 10, atol=tol * 10 * ref_q.abs().max())
    # and the whole cost through both paths (the kernel skips the clamping when the reach ball lies in the box)
    terms = {}
    for compiled in (True, False):
        c = CollisionCost(task, "official")
        with kernels.use("compiled" if compiled else "torch", "collision"):
            terms[compiled] = c(CostInput(dense, task, env, ee_goal, "nearest"), 2.0)
    torch.testing.assert_close(terms[True].value, terms[False].value, rtol=1e-6, atol=0)
    scale = terms[False].g_q.abs().max().item()
    torch.testing.assert_close(terms[True].g_q, terms[False].g_q, rtol=1e-5, atol=1e-6 * scale)


@pytest.mark.parametrize("task_name", ["EnvSpheres3D-RobotPanda", "EnvWarehouse-RobotPanda"])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_compiled_collision_pass_with_the_merged_block_table_is_the_torch_path(task_name, dtype):
    """Within the robot's reach the kernel reads one table where the grid box holds the reach ball: the fixed and
    the extra objects' grids merged (the extra row where strictly closer) and cut to the nodes that can be nearest
    to a point of the ball (elsewhere each set's distances apart from its gradients, whole). For
    sphere centres spread over that ball, and exactly half-way between nodes (rounding ties), on the ball's
    surface, and where the two object sets are equally far (the fixed set's gradient wins): the same active
    entries, the same cost and centre gradients as the torch path's two full-grid lookups."""
    from mpd.costs import collision_kernel

    task = load_task(task_name)
    env = task.env(extra_objects=True)
    reach = task.robot.chain.reach
    tables, clamp = collision_kernel.lookup_tables(env, dtype, reach)
    grid = env.grid("fixed")
    if task_name == "EnvSpheres3D-RobotPanda":  # its grid box holds the reach ball: one table, cut
        assert (
            not clamp and len(tables) == 1 and tables[0][0].size < 0.4 * grid.shape[0] * grid.shape[1] * grid.shape[2]
        )
    else:  # EnvWarehouse's box does not: the points are clamped into it, the two sets read apart
        assert clamp and len(tables) == 2
    g = torch.Generator().manual_seed(11)
    S, N = 40, 3000
    v = torch.randn(S, 3, N, generator=g, dtype=dtype)
    X = v / v.norm(dim=1, keepdim=True) * reach * torch.rand(S, 1, N, generator=g, dtype=dtype) ** (1 / 3)
    X[:, :, : N // 10] *= reach / X[:, :, : N // 10].norm(dim=1, keepdim=True)  # on the ball's surface
    lo = torch.as_tensor(grid.lo, dtype=dtype).view(1, 3, 1)
    ties = lo + (((X[:, :, N // 10 : N // 5] - lo) / grid.cell).floor() + 0.5) * grid.cell
    X[:, :, N // 10 : N // 5] = ties * (ties.norm(dim=1, keepdim=True) <= reach) + X[:, :, N // 10 : N // 5] * (
        ties.norm(dim=1, keepdim=True) > reach
    )
    # nodes where both sets are equally far (e.g. both far from everything or the same object)
    fixed, extra = env.grid("fixed"), env.grid("extra")
    nodes = torch.cartesian_prod(*[torch.arange(n) for n in fixed.shape])
    nodes = nodes[torch.randperm(len(nodes), generator=g)[:200000]]
    pos = torch.as_tensor(fixed.lo) + nodes.double() * fixed.cell
    idx = (nodes * torch.as_tensor(fixed._strides)).sum(-1)
    tie = (fixed._packed[idx, 0] == extra._packed[idx, 0]) & (pos.norm(dim=-1) <= reach)
    assert tie.any()
    tp = pos[tie][: N // 10].to(dtype)
    X[0, :, N // 5 : N // 5 + len(tp)] = tp.t()
    radius = torch.rand(S, 1, generator=g, dtype=dtype) * 0.3
    w = torch.rand(N, generator=g, dtype=dtype)
    value, flat, rows, _ = collision_kernel.collision_pass(env, X, radius, w, 2.0, reach=reach)
    d, gd = sdf_batch_last(env, X, "nearest")
    relu = (radius - d).clamp_min(0)
    assert torch.equal(flat, (relu > 0).reshape(-1).nonzero().squeeze(1))
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(value, (relu * w).sum(0), rtol=tol, atol=0)
    ref_G = (relu > 0)[:, None] * (-2.0 * w) * gd
    G = torch.zeros_like(ref_G)
    G[flat // N, :, flat % N] = rows
    torch.testing.assert_close(G, ref_G, rtol=tol, atol=0)
    # ``max_entries``: the entries come back when there are at most that many, else only the value
    E = flat.numel()
    capped = collision_kernel.collision_pass(env, X, radius, w, 2.0, reach=reach, max_entries=E)
    assert torch.equal(capped[1], flat) and torch.equal(capped[2], rows) and torch.equal(capped[0], value)
    over = collision_kernel.collision_pass(env, X, radius, w, 2.0, reach=reach, max_entries=E - 1)
    assert over[1] is None and over[2] is None and torch.equal(over[0], value)


@pytest.mark.parametrize("key", ["panda_spheres", "planar4"])
def test_compiled_passes_do_not_depend_on_the_thread_split(key, monkeypatch):
    """The compiled passes split the configurations over threads; every split gives identical results."""
    from mpd.costs import collision_kernel, self_collision_kernel
    from mpd.costs.self_collision import SelfCollisionCost

    task, param, env, free, q_start, q_goal, ee_goal = case(key, "bspline")
    dense = param.dense(free.float(), q_start.float(), None if q_goal is None else q_goal.float())
    kin = CostInput(dense, task, env, ee_goal, "nearest").kinematics()
    X = kin.points_t
    radius = (task.robot.sphere_radii + 0.05).to(X)[:, None]
    w = torch.rand(dense.q.shape[1], generator=torch.Generator().manual_seed(1))
    cost = SelfCollisionCost(task, "official")
    sargs = self_collision_kernel.kernel_args(
        cost._levels, cost.blocks, cost._used, task.robot.sphere_radii.numpy(), 0.05, X.dtype
    )
    n_threads = torch.get_num_threads()
    out = {}
    try:
        for threads, min_cols in ((1, 2048), (3, 7), (4, 1)):
            torch.set_num_threads(threads)
            monkeypatch.setattr(collision_kernel, "MIN_COLUMNS_PER_THREAD", min_cols)
            assert len(collision_kernel.column_ranges(X.shape[2])) == max(1, min(threads, X.shape[2] // min_cols))
            chain = task.robot.chain
            frames = (chain.point_joint + 1, chain.dof)
            out[threads] = (
                *collision_kernel.collision_pass(env, X, radius, w, 2.0, reach=None, frames=frames),
                *self_collision_kernel.self_pass(X, sargs, (kin, w, chain)),
            )
    finally:
        torch.set_num_threads(n_threads)
    assert out[1][1].numel() > 0 and out[1][5].numel() > 0 and out[1][8].abs().sum() > 0
    for threads in (3, 4):
        for a, b in zip(out[1], out[threads]):
            assert torch.equal(a, b)


@pytest.mark.parametrize("kind", ["bspline", "waypoints"])
@pytest.mark.parametrize("preset", ["official", "paper"])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("key", ["pointmass", "panda_spheres"])
def test_fused_phase_pass_is_the_torch_path(key, dtype, preset, kind):
    """Velocity, acceleration and joint limits in one compiled pass (``mpd.costs.phase_kernel``) against each cost's
    torch ``__call__``: the unweighted values and the weighted gradients w.r.t. q, q', q''; the point mass has
    position limits only, the Panda all three, both with violations (``_make_case``); then the whole cost
    function with the pass and without it."""
    from mpd.costs import phase_kernel

    task, param, env, free, q_start, q_goal, ee_goal = case(key, kind)
    free, q_start = free.to(dtype), q_start.to(dtype)
    q_goal = None if q_goal is None else q_goal.to(dtype)
    dense = param.dense(free, q_start, q_goal)
    assert kernels.supported(dense.stacked)
    inp = CostInput(dense, task, env, None, "nearest")
    weights = {"velocity": 0.7, "acceleration": 1.3, "joint_limits": 2.0}
    costs = [COSTS[name](task, preset) for name in weights]
    values, G = phase_kernel.phase_pass(
        dense.stacked, costs[0].weights(inp), [(c.penalty(inp), weights[c.name]) for c in costs]
    )
    ref_g = torch.zeros_like(G)
    tol = {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    for c, v in zip(costs, values):
        term = c(inp, weights[c.name])
        assert (term.value > 0).any()
        torch.testing.assert_close(v, term.value, **tol)
        for k, gk in enumerate((term.g_q, term.g_dq, term.g_ddq)):
            if gk is not None:
                ref_g[:, k] += gk
    torch.testing.assert_close(G, ref_g, **tol)
    assert G[:, 0].abs().max() > 0 and G.stride() == dense.stacked.stride()
    # the chain rule of the stacked gradient is the one of the three fields
    torch.testing.assert_close(param.grad_to_free_stacked(G), param.grad_to_free(G[:, 0], G[:, 1], G[:, 2]), **tol)
    # the cost function with and without the fused pass
    cf = CostFunction(task, param, env, preset=preset, sdf_mode="nearest")
    assert {c.name for c, _ in cf.fused} == set(weights)
    with_pass = cf(free, q_start, q_goal, None if ee_goal is None else tuple(x.to(dtype) for x in ee_goal))
    with kernels.use("torch", "phase"):
        without = cf(free, q_start, q_goal, None if ee_goal is None else tuple(x.to(dtype) for x in ee_goal))
    torch.testing.assert_close(with_pass.total, without.total, **tol)
    torch.testing.assert_close(with_pass.grad, without.grad, **tol)
    with pytest.raises(ValueError, match="two norm penalties on dense field 1"):
        phase_kernel.phase_pass(dense.stacked, costs[0].weights(inp), [(costs[0].penalty(inp), 1.0)] * 2)


def test_joint_limit_margin_is_in_time_units():
    """The authors' joint-limit cost takes eps = 0.03 off the velocity (rad/s) and acceleration (rad/s^2) limits in
    time units, then scales them to the phase (x T, x T^2): a velocity 0.02 rad/s under the limit is penalised (with
    the margin in phase units it would be 0.003 rad/s and not penalised), one 0.04 rad/s under it is not; the same
    for accelerations; the fused pass (CostFunction) sees the same bounds."""
    from mpd.costs.joint_limits import MARGIN
    from mpd.trajectory.base import Dense

    task = load_task("EnvWarehouse-RobotPanda")
    r, T, n = task.robot, 10.0, 16
    cost = COSTS["joint_limits"](task, "official")
    mid = ((r.q_min + r.q_max) / 2).to(F64)
    for which, lim, scale in (("dq", r.dq_max, T), ("ddq", r.ddq_max, T**2)):
        for under, penalised in ((0.02, True), (0.04, False)):
            x = torch.zeros(1, n, task.dof, dtype=F64)
            x[0, n // 2, 0] = (lim[0] - under) * scale  # joint 1 at one point, in phase units
            q = mid.expand(1, n, -1).clone()
            dense = Dense(
                q, x if which == "dq" else torch.zeros_like(x), x if which == "ddq" else torch.zeros_like(x), T
            )
            term = cost(CostInput(dense, task, task.env()))
            g = term.g_dq if which == "dq" else term.g_ddq
            expected = (MARGIN - under) * scale if penalised else 0.0
            w = cost.weights(CostInput(dense, task, task.env()))[n // 2]
            torch.testing.assert_close(g[0, n // 2, 0], torch.tensor(expected, dtype=F64) * w)
            assert (float(term.value[0]) > 0) == penalised
