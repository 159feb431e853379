"""Speed of the foundation's hot paths on CPU, float32:

(a) FK of all 56 collision spheres + the end-effector Jacobian for 12,800 Panda configurations
    (100 trajectories x 128 points, what one cost-gradient step of the planner needs); pytorch-kinematics'
    generic FK doing the same work is a second entry, for the ratio (target: ours <= 15 ms on 2 cores);
(b) validity of 100 x 128 Panda configurations (scene via the nearest-node grid SDF, self collision, joint
    position / velocity / acceleration limits) in EnvWarehouse.

Run: ``pytest benchmarks/test_bench_foundation.py -m benchmark --benchmark-only`` (``nox -s benchmarks``).
"""

from __future__ import annotations

import pytest
import torch

from mpd.collision import CollisionChecker
from mpd.robots import get_robot, pk_serial_chain
from mpd.tasks import load_task
from mpd.trajectory import make_parametrization

pytestmark = pytest.mark.benchmark

N = 100 * 128


@pytest.fixture(params=[1, 2], ids=lambda n: f"threads{n}")
def threads(request):
    """Both thread counts: on a shared 2-core machine one thread is often the faster (no waiting on a
    descheduled partner thread at every small op)."""
    old = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def panda():
    return get_robot("RobotPanda")


@pytest.fixture(scope="module")
def q32(panda):
    return panda.random_q(N, torch.Generator().manual_seed(0), dtype=torch.float32)


def test_fk_spheres_and_ee_jacobian(benchmark, threads, panda, q32):
    chain = panda.chain

    def run():
        kin = chain.forward(q32)
        return kin.points, chain.ee_jacobian(kin)

    pts, J = benchmark(run)
    assert pts.shape == (N, 56, 3) and J.shape == (N, 6, 7) and pts.dtype == torch.float32


def test_fk_spheres_and_ee_jacobian_pytorch_kinematics(benchmark, threads, panda, q32):
    """The same outputs through pytorch-kinematics: FK of all links, sphere centres per link, Jacobian."""
    pk = pk_serial_chain(str(panda.spec.urdf.resolve()), panda.spec.urdf.end_link)
    pk = pk.to(dtype=torch.float32)
    links = list(dict.fromkeys(panda.sphere_links))
    local = {
        name: torch.tensor([s.centre for s in panda.spec.spheres if s.link == name], dtype=torch.float32)
        for name in links
    }

    def run():
        frames = pk.forward_kinematics(q32, end_only=False)
        pts = []
        for name in links:
            T = frames[name].get_matrix()
            pts.append(local[name] @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3])
        return torch.cat(pts, 1), pk.jacobian(q32)

    pts, J = benchmark(run)
    ours = panda.chain.forward(q32[:64])
    torch.testing.assert_close(pts[:64], ours.points, rtol=0, atol=1e-5)
    torch.testing.assert_close(J[:64], panda.chain.ee_jacobian(ours), rtol=0, atol=1e-5)


def test_validity_warehouse_grid(benchmark, threads):
    task = load_task("EnvWarehouse-RobotPanda")
    checker = CollisionChecker(task, sdf_mode="nearest")
    checker.env.grid("fixed")  # built once (about 1.6 M nodes), outside the timing
    par = make_parametrization(task)
    g = torch.Generator().manual_seed(1)
    robot = task.robot
    qs = robot.random_q(100, g)
    w = robot.random_q(100 * par.n_free, g).reshape(100, par.n_free, 7)
    d = par.dense(w.float(), qs.float())
    q, dq, ddq = d.q, d.dq_dt, d.ddq_dt2
    assert q.shape == (100, 128, 7)

    v = benchmark(checker.trajectories, q, dq, ddq)
    assert v.valid.shape == (100,)
