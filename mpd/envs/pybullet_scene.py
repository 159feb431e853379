"""A task scene in PyBullet (DIRECT mode): exact collision geometry for data generation and for checking the
sphere model.

Obstacles come from an :class:`~mpd.envs.Environment` (its world-frame primitives, extra objects and rotation
included). 2-D scenes are lifted the way the authors' generator does it: a disc becomes a sphere centred at z
= 0, a 2-D box a box of height 0.05 centred at z = 0. Obstacles are static bodies with compound collision
shapes of up to 16 primitives each (PyBullet's limit), so that one ``getClosestPoints`` call per body answers
the environment query.

The robot is built from its description's ``[pybullet]`` section: ``source = "urdf"`` loads the URDF (the
Panda: pybullet_data's ``franka_panda/panda.urdf``, fingers held at ``urdf.fixed_joints``), ``source =
"shapes"`` writes a URDF from the robot's ``[[joints]]`` and ``[[pybullet.shapes]]`` into a temporary file.

Validity of a configuration:
    * environment: every robot link except the root (``panda_link0`` stands on the table) keeps a distance
      greater than ``clearance`` from every obstacle (closest points with distance <= clearance: collision);
    * self collision: no penetration (closest distance <= 0) on a chosen set of link pairs: ``"sphere_pairs"``
      (the sphere model's ``self_collision.link_pairs``, each sphere-model link standing for the PyBullet
      links rigidly attached to it: the Panda hand with its fingers), ``"all"`` (every pair of links with
      collision geometry that are not adjacent; links without geometry, like ``panda_link8``, are skipped over
      when deciding adjacency) or ``"none"``.
Link world poses are URDF link frames (``getLinkState(...)[4:6]``), not centres of mass.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Sequence
from typing import Literal

import numpy as np

from mpd.envs.environment import Environment
from mpd.robots.robot import Robot

SelfPairs = Literal["none", "sphere_pairs", "all"]
HEIGHT_2D = 0.05  # thickness of a 2-D box lifted to 3-D (the authors' value)


def _matrix_to_quat_xyzw(r: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_quat().tolist()


def _fmt(v: Iterable[float]) -> str:
    return " ".join(repr(float(x)) for x in v)


def chain_urdf(robot: Robot) -> str:
    """URDF text of a robot described by ``[[joints]]`` and ``[[pybullet.shapes]]`` (planar arms, points)."""
    spec = robot.spec
    if not spec.joints:
        raise ValueError(f"{robot.name}: no [[joints]] to build a URDF from")
    lims = dict(zip(robot.joint_names, spec.limits.position))
    links = [spec.joints[0].parent] + [j.child for j in spec.joints]
    shapes: dict[str, list] = {}
    for s in spec.pybullet.shapes:
        if s.link not in links:
            raise ValueError(f"{robot.name}: pybullet shape on unknown link {s.link!r}")
        shapes.setdefault(s.link, []).append(s)
    out = [f'<?xml version="1.0"?>\n<robot name="{robot.name}">']
    for name in links:
        out.append(f'  <link name="{name}">')
        # a token inertia: the body is only posed, never simulated, but PyBullet wants a mass on moving links
        out.append(
            '    <inertial><mass value="0.1"/>'
            '<inertia ixx="1e-4" iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/>'
            "</inertial>"
        )
        for s in shapes.get(name, []):
            if s.shape == "sphere":
                geom = f'<sphere radius="{s.radius!r}"/>'
            elif s.shape == "cylinder":
                geom = f'<cylinder radius="{s.radius!r}" length="{s.length!r}"/>'
            else:
                geom = f'<box size="{_fmt(s.size)}"/>'
            out.append(
                f'    <collision><origin xyz="{_fmt(s.xyz)}" rpy="{_fmt(s.rpy)}"/><geometry>{geom}</geometry>'
                "</collision>"
            )
        out.append("  </link>")
    for j in spec.joints:
        out.append(f'  <joint name="{j.name}" type="{j.type}">')
        out.append(f'    <parent link="{j.parent}"/><child link="{j.child}"/>')
        out.append(f'    <origin xyz="{_fmt(j.xyz)}" rpy="{_fmt(j.rpy)}"/>')
        if j.type != "fixed":
            lo, hi = lims[j.name]
            out.append(
                f'    <axis xyz="{_fmt(j.axis)}"/><limit lower="{lo!r}" upper="{hi!r}" effort="100" velocity="10"/>'
            )
        out.append("  </joint>")
    out.append("</robot>\n")
    return "\n".join(out)


class PyBulletScene:
    """One PyBullet DIRECT client holding a robot and (optionally) a task environment.

    Args:
        robot: the robot (its ``[pybullet]`` section says how it is built).
        env: the obstacles; ``None`` for the robot alone.
        clearance: required robot-obstacle distance (m); distance <= clearance is a collision.
        self_pairs: which link pairs are checked for self collision (see the module docstring).
    """

    def __init__(
        self,
        robot: Robot,
        env: Environment | None = None,
        *,
        clearance: float = 0.0,
        self_pairs: SelfPairs = "sphere_pairs",
    ):
        import pybullet as p

        self._p = p
        self.robot = robot
        self.env = env
        self.clearance = float(clearance)
        self.cid = p.connect(p.DIRECT)
        try:
            self._load_robot()
            self._load_obstacles()
            self.self_pairs_kind = self_pairs
            self.self_pairs = self._self_pairs(self_pairs)
        except Exception:
            self.close()
            raise

    # ------------------------------------------------------------------ building
    def _load_robot(self) -> None:
        p, spec = self._p, self.robot.spec
        if spec.pybullet.source == "urdf":
            if spec.urdf is None:
                raise ValueError(f"{self.robot.name}: [pybullet] source = 'urdf' needs a [urdf] section")
            self.body = p.loadURDF(str(spec.urdf.resolve()), useFixedBase=True, physicsClientId=self.cid)
            fixed = dict(spec.urdf.fixed_joints)
        else:
            fd, path = tempfile.mkstemp(suffix=".urdf", prefix=f"mpd-{self.robot.name}-")
            try:
                with os.fdopen(fd, "w") as f:
                    f.write(chain_urdf(self.robot))
                self.body = p.loadURDF(path, useFixedBase=True, physicsClientId=self.cid)
            finally:
                os.unlink(path)
            fixed = {}
        n = p.getNumJoints(self.body, physicsClientId=self.cid)
        info = [p.getJointInfo(self.body, j, physicsClientId=self.cid) for j in range(n)]
        self.root_link = p.getBodyInfo(self.body, physicsClientId=self.cid)[0].decode()
        self.link_index = {self.root_link: -1} | {i[12].decode(): i[0] for i in info}
        self.link_parent = {i[12].decode(): (info[i[16]][12].decode() if i[16] >= 0 else self.root_link) for i in info}
        joint_index = {i[1].decode(): i[0] for i in info}
        missing = [j for j in list(self.robot.joint_names) + list(fixed) if j not in joint_index]
        if missing:
            raise ValueError(f"{self.robot.name}: joints {missing} are not in the PyBullet model")
        self._q_joints = [joint_index[j] for j in self.robot.joint_names]
        self._fixed_joints = [joint_index[j] for j in fixed]
        self._fixed_values = [[float(v)] for v in fixed.values()]
        self._set_joints = self._q_joints + self._fixed_joints
        # links carried by joints the planner does not move (fixed joints, held fingers) go with their parent
        held = {info[joint_index[j]][12].decode() for j in fixed}
        held |= {i[12].decode() for i in info if i[2] == p.JOINT_FIXED}
        self.has_geometry = {
            name: bool(p.getCollisionShapeData(self.body, idx, physicsClientId=self.cid))
            for name, idx in self.link_index.items()
        }
        # the sphere-model link a PyBullet link moves with: the Panda fingers with panda_hand, link_ee of the
        # planar arms with their last link (which carries the end-effector sphere)
        sphere_links = set(self.robot.sphere_links)
        self.rigid_owner = {}
        for name in self.link_index:
            owner = name
            while owner in held and owner not in sphere_links:
                owner = self.link_parent[owner]
            self.rigid_owner[name] = owner
        self.set_q(np.zeros(self.robot.dof))

    def _load_obstacles(self) -> None:
        p = self._p
        self.obstacle_bodies: list[int] = []
        self._env_skip = {-1}
        if self.env is None or not self.env.primitives:
            return
        kinds, radii, halves, lengths, poss, quats = [], [], [], [], [], []
        for prim, _extra in self.env.primitives:
            c = np.zeros(3)
            c[: len(prim.centre)] = prim.centre
            if prim.kind == "sphere":
                kinds.append(p.GEOM_SPHERE)
                radii.append(float(prim.radius))
                halves.append([0.0, 0.0, 0.0])
                quats.append([0.0, 0.0, 0.0, 1.0])
            else:
                h = np.full(3, HEIGHT_2D / 2)
                h[: len(prim.half_size)] = prim.half_size
                r = np.eye(3)
                d = prim.rotation.shape[0]
                r[:d, :d] = prim.rotation
                kinds.append(p.GEOM_BOX)
                radii.append(0.0)
                halves.append(h.tolist())
                quats.append(_matrix_to_quat_xyzw(r))
            lengths.append(0.0)
            poss.append(c.tolist())
        # PyBullet keeps at most 16 shapes in a compound (MAX_COMPOUND_COLLISION_SHAPES): one body per 16
        self.obstacle_bodies = []
        for i in range(0, len(kinds), 16):
            sl = slice(i, i + 16)
            shape = p.createCollisionShapeArray(
                kinds[sl],
                radii=radii[sl],
                halfExtents=halves[sl],
                lengths=lengths[sl],
                collisionFramePositions=poss[sl],
                collisionFrameOrientations=quats[sl],
                physicsClientId=self.cid,
            )
            if shape < 0:
                raise RuntimeError("PyBullet refused the obstacle shapes")
            self.obstacle_bodies.append(p.createMultiBody(0.0, shape, -1, [0, 0, 0], physicsClientId=self.cid))
        n_shapes = sum(len(p.getCollisionShapeData(b, -1, physicsClientId=self.cid)) for b in self.obstacle_bodies)
        if n_shapes != len(kinds):
            raise RuntimeError(f"PyBullet built {n_shapes} obstacle shapes out of {len(kinds)}")
        # the root link never moves; the Panda's base dips 4 mm into the Warehouse table it stands on
        self._env_skip = {-1}

    def _self_pairs(self, kind: SelfPairs) -> list[tuple[int, int]]:
        if kind == "none":
            return []
        geo = [n for n, g in self.has_geometry.items() if g]
        if kind == "sphere_pairs":
            pairs = set()
            for a, b in self.robot.spec.self_collision.link_pairs:
                ga = [n for n in geo if self.rigid_owner[n] == a]
                gb = [n for n in geo if self.rigid_owner[n] == b]
                pairs |= {tuple(sorted((self.link_index[x], self.link_index[y]))) for x in ga for y in gb}
            return sorted(pairs)
        if kind != "all":
            raise ValueError(f"unknown self-collision pair set {kind!r} (none, sphere_pairs, all)")

        def geometric_parent(name: str) -> str | None:
            while name != self.root_link:
                name = self.link_parent[name]
                if self.has_geometry[name]:
                    return name
            return None

        gp = {n: geometric_parent(n) for n in geo}
        pairs = []
        for i, a in enumerate(geo):
            for b in geo[i + 1 :]:
                if gp[a] == b or gp[b] == a:
                    continue
                pairs.append(tuple(sorted((self.link_index[a], self.link_index[b]))))
        return sorted(pairs)

    def close(self) -> None:
        if getattr(self, "cid", None) is not None:
            try:
                self._p.disconnect(physicsClientId=self.cid)
            except Exception:  # already gone (interpreter shutdown)
                pass
            self.cid = None

    def __del__(self):
        self.close()

    def __enter__(self) -> PyBulletScene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ queries
    def set_q(self, q: Sequence[float]) -> None:
        vals = [[float(v)] for v in q] + self._fixed_values
        self._p.resetJointStatesMultiDof(self.body, self._set_joints, vals, physicsClientId=self.cid)

    def link_frame(self, link: str) -> tuple[np.ndarray, np.ndarray]:
        """World position (3,) and quaternion xyzw (4,) of a link's URDF frame at the current state."""
        idx = self.link_index[link]
        if idx < 0:
            pos, quat = self._p.getBasePositionAndOrientation(self.body, physicsClientId=self.cid)
            # PyBullet reports the base's inertial frame; the URDF frame is where the body was placed
            inert = self._p.getDynamicsInfo(self.body, -1, physicsClientId=self.cid)[3:5]
            pos, quat = self._p.multiplyTransforms(pos, quat, *self._p.invertTransform(*inert))
            return np.array(pos), np.array(quat)
        s = self._p.getLinkState(self.body, idx, computeForwardKinematics=True, physicsClientId=self.cid)
        return np.array(s[4]), np.array(s[5])

    def min_env_distance(self, q: Sequence[float] | None = None, max_distance: float = 1.0) -> float:
        """Closest robot-obstacle distance (negative: penetration), capped at ``max_distance``."""
        if q is not None:
            self.set_q(q)
        d = [float(max_distance)]
        for ob in self.obstacle_bodies:
            pts = self._p.getClosestPoints(self.body, ob, max_distance, physicsClientId=self.cid)
            d += [c[8] for c in pts if c[3] not in self._env_skip]
        return min(d)

    def env_free(self, q: Sequence[float] | None = None, clearance: float | None = None) -> bool:
        if q is not None:
            self.set_q(q)
        m = self.clearance if clearance is None else float(clearance)
        for ob in self.obstacle_bodies:
            pts = self._p.getClosestPoints(self.body, ob, m, physicsClientId=self.cid)
            if any(c[8] <= m and c[3] not in self._env_skip for c in pts):
                return False
        return True

    def self_free(self, q: Sequence[float] | None = None) -> bool:
        if q is not None:
            self.set_q(q)
        gcp, body, cid = self._p.getClosestPoints, self.body, self.cid
        for a, b in self.self_pairs:
            if any(c[8] <= 0.0 for c in gcp(body, body, 0.0, a, b, physicsClientId=cid)):
                return False
        return True

    def is_valid(self, q: Sequence[float]) -> bool:
        self.set_q(q)
        return self.env_free() and self.self_free()

    def check(self, q: np.ndarray, clearance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Environment-free and self-free flags of configurations q (M, dof)."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, self.robot.dof)
        env = np.empty(len(q), dtype=bool)
        slf = np.empty(len(q), dtype=bool)
        for i, qi in enumerate(q):
            self.set_q(qi)
            env[i] = self.env_free(clearance=clearance)
            slf[i] = self.self_free()
        return env, slf

    def valid(self, q: np.ndarray) -> np.ndarray:
        env, slf = self.check(q)
        return env & slf
