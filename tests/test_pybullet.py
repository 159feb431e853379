"""PyBullet scenes: kinematics against PyBullet's link frames, obstacles, clearance, self-collision pairs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mpd.envs.pybullet_scene import PyBulletScene, chain_urdf
from mpd.robots import get_robot
from mpd.tasks import load_task


@pytest.fixture(scope="module")
def panda_scene():
    with PyBulletScene(get_robot("RobotPanda")) as sc:
        yield sc


def _frame(scene, link, q):
    scene.set_q(q)
    pos, quat = scene.link_frame(link)
    return pos, Rotation.from_quat(quat).as_matrix()


def test_panda_ee_matches_pybullet(panda_scene):
    robot = panda_scene.robot
    q = robot.random_q(1000, torch.Generator().manual_seed(0))
    pos, rot = robot.ee_pose(q)
    ep, er = [], []
    for qi, p, r in zip(q.numpy(), pos.numpy(), rot.numpy()):
        pb, rb = _frame(panda_scene, robot.spec.ee_link, qi)
        ep.append(np.linalg.norm(p - pb))
        er.append(Rotation.from_matrix(r.T @ rb).magnitude())
    assert max(ep) <= 1e-4
    assert max(er) <= 1e-3


@pytest.mark.parametrize("name", ["RobotPanda", "RobotPlanar2Link", "RobotPlanar4Link", "RobotPointMass2D"])
def test_sphere_centres_are_link_frames_times_offsets(name):
    robot = get_robot(name)
    q = robot.random_q(50, torch.Generator().manual_seed(1))
    centres = robot.sphere_centres(q).numpy()
    offsets = np.array([s.centre for s in robot.spec.spheres])
    with PyBulletScene(robot) as sc:
        for qi, ci in zip(q.numpy(), centres):
            sc.set_q(qi)
            frames = {link: sc.link_frame(link) for link in set(robot.sphere_links)}
            for k, link in enumerate(robot.sphere_links):
                p, quat = frames[link]
                c = p + Rotation.from_quat(quat).as_matrix() @ offsets[k]
                assert np.allclose(c[: robot.task_dim], ci[k], atol=1e-5), (link, k)


def test_reference_fk_values(panda_scene):
    """The numbers of docs/PAPER_VS_CODE.md, "URDF check"."""
    panda = get_robot("RobotPanda")
    for q, p_ref, r_ref in [
        (np.zeros(7), [0.088, 0.0, 0.926], [[0.70711, 0.70711, 0], [0.70711, -0.70711, 0], [0, 0, -1]]),
        (np.array([0, -0.785, 0, -2.356, 0, 1.571, 0.785]), [0.30702, 0.0, 0.59027], None),
    ]:
        p, r = panda.ee_pose(torch.as_tensor(q))
        assert np.allclose(p.numpy(), p_ref, atol=1e-5)
        pb, rb = _frame(panda_scene, "panda_hand", q)
        assert np.allclose(pb, p_ref, atol=1e-5)
        if r_ref is not None:
            assert np.allclose(r.numpy(), r_ref, atol=1e-5)
            assert np.allclose(rb, r_ref, atol=1e-5)
    for name, q, ref in [
        ("RobotPlanar2Link", [0.3, -0.5], [0.485087, -0.000497]),
        ("RobotPlanar4Link", [0.3, -0.5, 0.2, 1.0], [0.695141, 0.187664]),
    ]:
        robot = get_robot(name)
        p, _ = robot.ee_pose(torch.tensor(q, dtype=torch.float64))
        assert np.allclose(p.numpy()[:2], ref, atol=1e-6)
        with PyBulletScene(robot) as sc:
            assert np.allclose(_frame(sc, "link_ee", np.array(q))[0][:2], ref, atol=1e-6)


def test_chain_urdf_has_every_joint_and_shape():
    robot = get_robot("RobotPlanar4Link")
    text = chain_urdf(robot)
    assert text.count("<joint ") == len(robot.spec.joints)
    assert text.count("<collision>") == len(robot.spec.pybullet.shapes)


def test_obstacles_2d_lifted_and_more_than_16():
    """NarrowPassage with extra objects has 33 primitives: several compound bodies (limit 16)."""
    task = load_task("EnvNarrowPassageDense2D-RobotPointMass2D")
    env = task.env(extra_objects=True)
    with PyBulletScene(task.robot, env, clearance=0.0) as sc:
        assert len(sc.obstacle_bodies) == 3
        for prim, _ in env.primitives:  # the point mass at each obstacle's centre collides
            assert not sc.env_free(prim.centre)
        # a 2-D box is 5 cm high: a point at its centre penetrates by half the height plus its radius
        box = next(p for p, _ in env.primitives if p.kind == "box")
        assert sc.min_env_distance(box.centre) == pytest.approx(-(0.025 + 0.02), abs=1e-6)


def test_clearance_is_distance_threshold():
    task = load_task("EnvSimple2D-RobotPointMass2D")
    env = task.env()
    disc = env.primitives[0][0]
    gap = 0.015  # robot surface 1.5 cm from the disc
    q = disc.centre + np.array([disc.radius + 0.02 + gap, 0.0])
    with PyBulletScene(task.robot, env, clearance=0.01) as sc:
        assert sc.min_env_distance(q) == pytest.approx(gap, abs=1e-6)
        assert sc.env_free(q)
        assert not sc.env_free(q, clearance=0.02)


def test_panda_base_is_not_an_obstacle_and_pairs():
    task = load_task("EnvWarehouse-RobotPanda")
    with PyBulletScene(task.robot, task.env(), self_pairs="sphere_pairs") as sc:
        names = {v: k for k, v in sc.link_index.items()}
        pairs = {(names[a], names[b]) for a, b in sc.self_pairs}
        # the sphere model's panda_hand stands for the hand and both fingers
        assert ("panda_link1", "panda_rightfinger") in pairs and ("panda_link2", "panda_hand") in pairs
        assert len(pairs) == 10
        q_home = np.array([0, -0.785, 0, -2.356, 0, 1.571, 0.785])
        assert sc.is_valid(q_home)  # panda_link0 touches the table top, which does not count
    with PyBulletScene(task.robot, None, self_pairs="all") as sc:
        names = {v: k for k, v in sc.link_index.items()}
        pairs = {(names[a], names[b]) for a, b in sc.self_pairs}
        assert ("panda_link7", "panda_hand") not in pairs  # rigidly joined through the geometry-less link8
        assert ("panda_link5", "panda_link7") in pairs
        assert sc.self_free(q_home)


@pytest.mark.slow
@pytest.mark.parametrize("task_name", ["EnvSpheres3D-RobotPanda", "EnvWarehouse-RobotPanda"])
def test_sphere_model_vs_meshes(task_name):
    """The measurement of datasets/README.md on 2,000 configurations (the README's numbers use 10,000)."""
    from mpd.data.measure import sphere_vs_mesh

    r = sphere_vs_mesh(load_task(task_name), n=2000)
    for scene in ("train", "extra"):
        env0 = r[f"{scene}/env sphere(0) vs mesh(0)"]
        assert env0["agree"] > 0.97 and env0["false_free"] < 0.015
        assert r[f"{scene}/env sphere(0.02) vs mesh(0)"]["false_free"] < 0.002  # the clearance covers the meshes
        assert r[f"{scene}/self sphere pairs vs mesh same pairs"]["agree"] > 0.98
