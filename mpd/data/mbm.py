"""MotionBenchMaker (MBM) problems for the Franka Panda, read into mpd's own form.

The source is the archive ``resources/panda/problems.tar.bz2`` of the ``vamp-planner`` source package (PyPI,
Apache-2.0); a copy is shipped in ``mpd/data/mbm/`` (``LICENSE-vamp.txt``, ``README.md``). It holds 7 families
(``table_pick``, ``table_under_pick``, ``box``, ``bookshelf_small``, ``bookshelf_tall``, ``bookshelf_thin``,
``cage``) of 100 problems each: per problem a MoveIt planning scene (``sceneNNNN.yaml``: collision objects made of
boxes, cylinders and spheres, each with a pose) and a motion plan request (``requestNNNN.yaml``: the start joint
state and a goal of one joint constraint per arm joint).

Frames. MBM's Panda (robowflex_resources) has ``panda_link0`` at the world origin, like mpd's (pybullet_data's
URDF, mounted at the origin), and the same kinematic chain; the scenes' fixed frame and the virtual joint are the
identity. So the scenes' world frame is mpd's world frame and the joint values carry over unchanged. MBM's hand
holds the fingers 6.5 cm from the hand's axis (fixed joints), mpd's at 4 cm; mpd's 56-sphere model covers the
fingers and the gap between them.

Primitives. MoveIt gives a box by its full side lengths, a cylinder by (height, radius) along its local z axis, a
sphere by its radius, and orientations as quaternions (x, y, z, w). The stored form keeps them as they are
(cylinders included). mpd's scenes have spheres and boxes only, so a cylinder enters a scene as the union of
``CYLINDER_SLABS`` boxes of half extents (r, r sin(pi / 2k), h / 2), turned about its axis by multiples of pi / k:
the union contains the cylinder and passes it by at most r (sqrt(1 + sin^2(pi / 2k)) - 1) at the slabs' edges (2.1
mm for MBM's 3 cm cans with k = 4; one circumscribed box, k = 1, passes it by r (sqrt(2) - 1), 1.2 cm, which put
the hand of every grasp goal of the table and bookshelf families into its can). VAMP uses capsules, and the
circumscribed box for the ``box`` family.

Grasp targets. Every MBM goal is a grasp: MBM's query configurations (``configs/scenes/<scene>/*queries*.yaml`` in
MBM's repository) name the objects a goal may grasp (``Can1`` on the tables and in the box, ``Cube1`` in the cage,
any ``Can*`` on the shelves) and the stored problems do not say which one was taken; :func:`grasped_object` names it
as the candidate whose centre is nearest MBM's grasp point (``GRASP_OFFSET`` along the hand's axis) at the goal.
``grasp_target`` says what becomes of it: ``"obstacle"`` (the default, the strict reading: it is an obstacle like
the others) or ``"ignored"`` (left out of the scene). mpd's hand spheres fill the gap between the fingers, which
MBM's hand holds open around the object, so under ``"obstacle"`` the box family's top-down grasps and every cage
goal put the hand into the grasped object; results with ``"ignored"`` are not comparable with numbers published on
MBM (docs/MBM.md).

The import is content addressed: its identity is the hash of the archive's sha256 and the importer's format
version, and its files (``<cache>/mbm/panda-<identity>/``: one JSON file of problems and one task file per family,
and ``index.json``) are written to temporary names and renamed.
"""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
import tarfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpd.data.storage import write_atomic
from mpd.envs.primitives import Primitive, quat_wxyz_to_matrix
from mpd.paths import cache_dir
from mpd.schema import file_sha256, stable_hash

FAMILIES = (
    "table_pick",
    "table_under_pick",
    "box",
    "bookshelf_small",
    "bookshelf_tall",
    "bookshelf_thin",
    "cage",
)
ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
SHIPPED = Path(__file__).parent / "mbm" / "panda-problems.tar.bz2"
SHIPPED_SHA256 = "4e1509e99c53da769ee6a338cf1173ecf601e4ec16f24081d3894ef358243b69"
# the vamp-planner release whose source package the shipped archive was taken from
SDIST_VERSION = "0.6.4"
SDIST_MEMBER = "resources/panda/problems.tar.bz2"
# bumped whenever the stored form or the mapping of primitives changes (a new identity, a new folder)
FORMAT_VERSION = 1


CYLINDER_SLABS = 4  # boxes per cylinder (see the module's docstring)

# What becomes of the object a goal grasps (see the module's docstring): an obstacle (the strict reading) or left out
GRASP_TARGETS = ("obstacle", "ignored")
# MBM's grasp point (robowflex_resources' panda_grasptarget): this far along the z axis of mpd's end-effector link
# (panda_hand), in m
GRASP_OFFSET = 0.105
# The objects a family's goals may grasp (MBM's query configurations): exact names, or a prefix ending in "*"
GRASP_CANDIDATES = {
    "table_pick": ("Can1",),
    "table_under_pick": ("Can1",),
    "box": ("Can1",),
    "bookshelf_small": ("Can*",),
    "bookshelf_tall": ("Can*",),
    "bookshelf_thin": ("Can*",),
    "cage": ("Cube1",),
}


@dataclass(frozen=True)
class Obstacle:
    """One MBM collision object, world frame: a sphere (``radius``), a box (``half_extents``, ``rotation_wxyz``) or a
    cylinder (``radius``, ``height`` along its local z axis, ``rotation_wxyz``)."""

    name: str
    kind: str  # "sphere" | "box" | "cylinder"
    centre: tuple[float, float, float]
    radius: float = 0.0
    half_extents: tuple[float, float, float] | None = None
    height: float = 0.0
    rotation_wxyz: tuple[float, float, float, float] | None = None

    def primitives(self, cylinder_slabs: int = CYLINDER_SLABS) -> list[Primitive]:
        """mpd's primitives of this object (a cylinder: ``cylinder_slabs`` boxes whose union contains it)."""
        c = np.asarray(self.centre, dtype=np.float64)
        if self.kind == "sphere":
            return [Primitive("sphere", c, radius=float(self.radius), name=self.name)]
        r = quat_wxyz_to_matrix(self.rotation_wxyz) if self.rotation_wxyz is not None else np.eye(3)
        if self.kind == "box":
            return [
                Primitive(
                    "box", c, half_size=np.asarray(self.half_extents, dtype=np.float64), rotation=r, name=self.name
                )
            ]
        if cylinder_slabs < 1:
            raise ValueError(f"cylinder_slabs must be at least 1, got {cylinder_slabs}")
        k = int(cylinder_slabs)
        half = np.array([self.radius, self.radius * np.sin(np.pi / (2 * k)), self.height / 2])
        out = []
        for j in range(k):
            a = np.pi * j / k
            turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
            out.append(Primitive("box", c, half_size=half.copy(), rotation=r @ turn, name=f"{self.name}#{j}"))
        return out

    def to_json(self) -> dict:
        d = {"name": self.name, "kind": self.kind, "centre": list(self.centre)}
        if self.kind in ("sphere", "cylinder"):
            d["radius"] = self.radius
        if self.kind == "cylinder":
            d["height"] = self.height
        if self.kind == "box":
            d["half_extents"] = list(self.half_extents)
        if self.kind != "sphere":
            d["rotation_wxyz"] = list(self.rotation_wxyz)
        return d

    @classmethod
    def from_json(cls, d: dict) -> Obstacle:
        return cls(
            name=d["name"],
            kind=d["kind"],
            centre=tuple(d["centre"]),
            radius=float(d.get("radius", 0.0)),
            half_extents=tuple(d["half_extents"]) if "half_extents" in d else None,
            height=float(d.get("height", 0.0)),
            rotation_wxyz=tuple(d["rotation_wxyz"]) if "rotation_wxyz" in d else None,
        )


@dataclass(frozen=True)
class Problem:
    family: str
    index: int
    start: tuple[float, ...]  # 7 joint positions (rad)
    goal: tuple[float, ...]
    obstacles: tuple[Obstacle, ...]

    @property
    def name(self) -> str:
        return f"{self.family}/{self.index:04d}"

    def primitives(self, cylinder_slabs: int = CYLINDER_SLABS, without: str | None = None) -> list[Primitive]:
        """The problem's scene as mpd primitives (world frame), to give at plan time; ``without``: the name of a
        collision object left out (every primitive of it)."""
        return [p for o in self.obstacles if object_name(o) != without for p in o.primitives(cylinder_slabs)]

    def to_json(self) -> dict:
        return {
            "index": self.index,
            "start": list(self.start),
            "goal": list(self.goal),
            "obstacles": [o.to_json() for o in self.obstacles],
        }


def object_name(o: Obstacle) -> str:
    """The MoveIt collision object an obstacle belongs to (an object of several primitives names them ``id#k``)."""
    return o.name.split("#", 1)[0]


def _is_candidate(name: str, patterns: tuple[str, ...]) -> bool:
    return any(name.startswith(p[:-1]) if p.endswith("*") else name == p for p in patterns)


def grasp_points(robot, goals) -> np.ndarray:
    """MBM's grasp point (``GRASP_OFFSET`` along the hand's z axis, world frame) of mpd's Panda at each goal:
    (n, 7) joint positions -> (n, 3)."""
    import torch

    pos, rot = robot.ee_pose(torch.as_tensor(np.asarray(goals, dtype=np.float64)).reshape(-1, 7))
    return (pos + rot[..., 2] * GRASP_OFFSET).numpy()


def grasped_object(problem: Problem, grasp_point) -> str:
    """The name of the collision object the problem's goal grasps: of the family's candidates
    (``GRASP_CANDIDATES``), the one whose centre is nearest ``grasp_point`` (:func:`grasp_points` at the goal)."""
    x = np.asarray(grasp_point, dtype=np.float64)
    centres: dict[str, list[np.ndarray]] = {}
    for o in problem.obstacles:
        if _is_candidate(object_name(o), GRASP_CANDIDATES[problem.family]):
            centres.setdefault(object_name(o), []).append(np.asarray(o.centre))
    if not centres:
        raise ValueError(f"{problem.name}: none of the objects {GRASP_CANDIDATES[problem.family]} in its scene")
    return min(centres, key=lambda n: float(np.linalg.norm(np.mean(centres[n], axis=0) - x)))


def scene_primitives(
    problem: Problem, robot, grasp_target: str = "obstacle", cylinder_slabs: int = CYLINDER_SLABS
) -> list[Primitive]:
    """The scene of a problem to give at plan time: every object (``grasp_target="obstacle"``) or all but the one
    its goal grasps (``"ignored"``); ``robot``: mpd's Panda (for the grasp point; unused under ``"obstacle"``)."""
    if grasp_target not in GRASP_TARGETS:
        raise ValueError(f"grasp_target {grasp_target!r} (one of {', '.join(GRASP_TARGETS)})")
    if grasp_target == "obstacle":
        return problem.primitives(cylinder_slabs)
    return problem.primitives(cylinder_slabs, without=grasped_object(problem, grasp_points(robot, [problem.goal])[0]))


# -- reading MoveIt's YAML ------------------------------------------------------------------------------------
def _yaml_load(text: bytes):
    # PyYAML comes with pytorch_kinematics (a dependency); its C loader when built with libyaml
    import yaml

    return yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


def _pose(p: dict) -> tuple[np.ndarray, np.ndarray]:
    """(position, rotation matrix) of a geometry_msgs/Pose as MoveIt writes it: orientation (x, y, z, w)."""
    x, y, z, w = (float(v) for v in p["orientation"])
    return np.asarray(p["position"], dtype=np.float64), quat_wxyz_to_matrix((w, x, y, z))


def _matrix_to_wxyz(r: np.ndarray) -> tuple[float, float, float, float]:
    """A unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method), w >= 0."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = (0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (r[j, i] + r[i, j]) / s
        v[k] = (r[k, i] + r[i, k]) / s
        q = ((r[k, j] - r[j, k]) / s, *v)
    q = np.asarray(q) / np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return tuple(float(v) for v in q)


def parse_scene(data: dict) -> list[Obstacle]:
    """The collision objects of a MoveIt planning scene as mpd obstacles (world frame)."""
    out = []
    for co in (data.get("world") or {}).get("collision_objects") or []:
        base_p, base_r = _pose(co["pose"]) if "pose" in co else (np.zeros(3), np.eye(3))
        prims, poses = co.get("primitives") or [], co.get("primitive_poses") or []
        if len(prims) != len(poses):
            raise ValueError(f"collision object {co['id']!r}: {len(prims)} primitives, {len(poses)} poses")
        for k, (prim, pose) in enumerate(zip(prims, poses)):
            p, r = _pose(pose)
            centre = base_p + base_r @ p
            rot = base_r @ r
            name = co["id"] if len(prims) == 1 else f"{co['id']}#{k}"
            kind, dims = prim["type"], [float(v) for v in prim["dimensions"]]
            c = tuple(float(v) for v in centre)
            if kind == "sphere":
                out.append(Obstacle(name, "sphere", c, radius=dims[0]))
            elif kind == "box":
                half = tuple(v / 2 for v in dims)
                out.append(Obstacle(name, "box", c, half_extents=half, rotation_wxyz=_matrix_to_wxyz(rot)))
            elif kind == "cylinder":  # shape_msgs/SolidPrimitive: dimensions (height, radius), axis = local z
                h, rad = dims
                out.append(Obstacle(name, "cylinder", c, radius=rad, height=h, rotation_wxyz=_matrix_to_wxyz(rot)))
            else:
                raise ValueError(f"collision object {co['id']!r}: primitive type {kind!r} (sphere, box, cylinder)")
    return out


def parse_request(data: dict) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(start, goal) arm joint positions of a MoveIt motion plan request with a joint-space goal."""
    js = data["start_state"]["joint_state"]
    pos = dict(zip(js["name"], js["position"]))
    start = tuple(float(pos[j]) for j in ARM_JOINTS)
    goals = data["goal_constraints"]
    if len(goals) != 1:
        raise ValueError(f"{len(goals)} goal constraints (one joint-space goal expected)")
    jc = {c["joint_name"]: float(c["position"]) for c in goals[0]["joint_constraints"]}
    missing = [j for j in ARM_JOINTS if j not in jc]
    if missing:
        raise ValueError(f"the goal has no constraint on {', '.join(missing)}")
    return start, tuple(jc[j] for j in ARM_JOINTS)


_MEMBER = re.compile(r"(?:^|/)problems/(?P<family>[a-z_]+)_panda/(?P<kind>scene|request)(?P<index>\d+)\.yaml$")


def read_archive(path: str | Path, families: tuple[str, ...] | None = None) -> dict[str, list[Problem]]:
    """The problems of MBM's Panda archive (``problems.tar.bz2``) or of a vamp-planner source package that holds it,
    per family, by index."""
    path = Path(path)
    want = set(FAMILIES if families is None else families)
    unknown = want - set(FAMILIES)
    if unknown:
        raise ValueError(f"unknown MBM families {sorted(unknown)} (known: {', '.join(FAMILIES)})")
    scenes: dict[tuple[str, int], list[Obstacle]] = {}
    requests: dict[tuple[str, int], tuple] = {}
    with _open_problems(path) as tar:
        for m in tar:
            match = _MEMBER.search(m.name) if m.isfile() else None
            if match is None or match["family"] not in want:
                continue
            key = (match["family"], int(match["index"]))
            data = _yaml_load(tar.extractfile(m).read())
            try:
                if match["kind"] == "scene":
                    scenes[key] = parse_scene(data)
                else:
                    requests[key] = parse_request(data)
            except (KeyError, ValueError) as e:
                raise ValueError(f"{path}: {m.name}: {e}") from None
    if set(scenes) != set(requests):
        odd = sorted(set(scenes) ^ set(requests))[:5]
        raise ValueError(f"{path}: scenes and requests do not pair up (e.g. {odd})")
    out: dict[str, list[Problem]] = {f: [] for f in FAMILIES if f in want}
    for fam, i in sorted(scenes):
        start, goal = requests[(fam, i)]
        out[fam].append(Problem(fam, i, start, goal, tuple(scenes[(fam, i)])))
    empty = [f for f, ps in out.items() if not ps]
    if empty:
        raise ValueError(f"{path}: no problems of {', '.join(empty)}")
    return out


class _open_problems:
    """The problems tar (bz2) itself, or the one inside a source package (``.tar.gz``)."""

    def __init__(self, path: Path):
        self.path = path
        self._outer = None

    def __enter__(self) -> tarfile.TarFile:
        if not self.path.is_file():
            raise FileNotFoundError(f"no such file: {self.path}")
        if self.path.name.endswith((".tar.gz", ".tgz")):
            self._outer = tarfile.open(self.path, "r:gz")
            inner = next((m for m in self._outer if m.name.endswith("/" + SDIST_MEMBER)), None)
            if inner is None:
                self._outer.close()
                raise ValueError(f"{self.path}: no {SDIST_MEMBER} in this source package")
            self._tar = tarfile.open(fileobj=self._outer.extractfile(inner), mode="r:bz2")
        else:
            self._tar = tarfile.open(self.path, "r:bz2")
        return self._tar

    def __exit__(self, *exc) -> None:
        self._tar.close()
        if self._outer is not None:
            self._outer.close()


def archive_sha256(path: str | Path) -> str:
    """sha256 of the problems archive itself (also when it is read from inside a source package)."""
    path = Path(path)
    if path.name.endswith((".tar.gz", ".tgz")):
        with tarfile.open(path, "r:gz") as outer:
            inner = next((m for m in outer if m.name.endswith("/" + SDIST_MEMBER)), None)
            if inner is None:
                raise ValueError(f"{path}: no {SDIST_MEMBER} in this source package")
            return hashlib.sha256(outer.extractfile(inner).read()).hexdigest()
    return file_sha256(path)


def download_sdist(dest: str | Path, version: str = SDIST_VERSION) -> Path:
    """The vamp-planner source package from PyPI with pip (only downloaded; pip prepares its metadata, which needs
    its build requirements as wheels but no compiler)."""
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    name = f"vamp_planner-{version}.tar.gz"
    if not (dest / name).is_file():
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", "vamp-planner"]
        subprocess.run([*cmd, "-d", str(dest), f"vamp-planner=={version}"], check=True, capture_output=True)
    return dest / name


# -- the stored form ---------------------------------------------------------------------------------------------
def task_name(family: str) -> str:
    return f"MBM-{family}-RobotPanda"


def task_toml(family: str) -> str:
    """The task file of a family: the Panda without fixed obstacles (each problem's scene is given at plan time),
    joint-space goals, checked without margin (MBM's problems are checked for contact, not for clearance)."""
    return f"""# MotionBenchMaker {family} (Panda): the scene of each problem is given at plan time (mpd bench mbm).
schema_version = 1
name = "{task_name(family)}"
description = "MotionBenchMaker {family}: a Franka Panda, each problem's own boxes and cylinders, joint-space goal."

[environment]
dim = 3
workspace = [[-1.5, -1.5, -0.5], [1.5, 1.5, 2.0]]
sdf_cell_size = 0.02
box_corner_radius = 0.0
obstacles = []

[robot]
name = "RobotPanda"

[context]
kind = "goal_joint_position"

[trajectory]
duration = 10.0
n_points = 128
bspline_degree = 5
n_control_points = 37

[collision]
cost_margin = 0.05
clearance = 0.0
validity_margin = 0.0
self_collision = true

[costs.weights]
collision = 10.0
self_collision = 1.0
joint_limits = 1.0
velocity = 0.01
acceleration = 0.001

[data]
planner_time_limit = 10.0
"""


@dataclass(frozen=True)
class Imported:
    """An import in the cache: its folder, identity, the archive's sha256 and the families it holds."""

    root: Path
    identity: str
    source_sha256: str
    families: tuple[str, ...]

    def task_path(self, family: str) -> Path:
        return self.root / f"{task_name(family)}.toml"

    def problems(self, family: str) -> list[Problem]:
        data = json.loads((self.root / f"{family}.json").read_text())
        return [
            Problem(
                family,
                int(p["index"]),
                tuple(p["start"]),
                tuple(p["goal"]),
                tuple(Obstacle.from_json(o) for o in p["obstacles"]),
            )
            for p in data["problems"]
        ]


def identity_of(source_sha256: str) -> str:
    return stable_hash({"source_sha256": source_sha256, "format": FORMAT_VERSION})


def import_problems(
    source: str | Path | None = None, families: tuple[str, ...] | None = None, root: str | Path | None = None
) -> Imported:
    """Read MBM's Panda problems (``source``: the archive, a vamp-planner source package, or None for the shipped
    copy) into ``<root or cache>/mbm/panda-<identity>/``. A family already there with the same content is kept."""
    src = SHIPPED if source is None else Path(source)
    sha = archive_sha256(src)
    ident = identity_of(sha)
    folder = Path(root) if root is not None else cache_dir() / "mbm"
    out = folder / f"panda-{ident}"
    out.mkdir(parents=True, exist_ok=True)
    fams = tuple(FAMILIES if families is None else families)
    index_path = out / "index.json"
    index = json.loads(index_path.read_text()) if index_path.is_file() else {"families": {}}
    todo = [f for f in fams if not _family_done(out, f, index)]
    if todo:
        problems = read_archive(src, tuple(todo))
        for fam in todo:
            body = json.dumps(
                {"family": fam, "source_sha256": sha, "problems": [p.to_json() for p in problems[fam]]},
                indent=None,
                separators=(",", ":"),
            ).encode()
            write_atomic(out / f"{fam}.json", body)
            write_atomic(out / f"{task_name(fam)}.toml", task_toml(fam).encode())
            index["families"][fam] = {
                "problems": len(problems[fam]),
                "sha256": hashlib.sha256(body).hexdigest(),
                "task": f"{task_name(fam)}.toml",
            }
        index.update(
            {
                "identity": ident,
                "source_sha256": sha,
                "format": FORMAT_VERSION,
                "source": "vamp-planner resources/panda/problems.tar.bz2 (MotionBenchMaker)",
            }
        )
        index["families"] = dict(sorted(index["families"].items(), key=lambda kv: FAMILIES.index(kv[0])))
        write_atomic(index_path, (json.dumps(index, indent=1) + "\n").encode())
    return Imported(out, ident, sha, tuple(f for f in FAMILIES if f in index["families"]))


def _family_done(out: Path, fam: str, index: dict) -> bool:
    rec = index.get("families", {}).get(fam)
    f = out / f"{fam}.json"
    return rec is not None and f.is_file() and (out / rec["task"]).is_file() and file_sha256(f) == rec["sha256"]


# -- validity of the starts and goals under mpd's checker ---------------------------------------------------------
def endpoint_validity(
    imported: Imported, family: str, cylinder_slabs: int = CYLINDER_SLABS, grasp_target: str = "obstacle"
) -> dict[str, np.ndarray]:
    """Per problem of a family, whether its start and goal are valid under mpd's ground-truth checker (the sphere
    model against the problem's scene, self collision, mpd's joint limits) and why not: arrays of shape (n,) for
    ``start_valid``, ``goal_valid`` and, per end, ``*_env_free``, ``*_self_free``, ``*_within_limits``.
    ``grasp_target``: the grasped object an obstacle (``"obstacle"``) or left out of the scene (``"ignored"``)."""
    import torch

    from mpd.collision import CollisionChecker
    from mpd.tasks import load_task

    task = load_task(imported.task_path(family))
    base = task.env()
    out: dict[str, list[bool]] = {}
    for p in imported.problems(family):
        prims = scene_primitives(p, task.robot, grasp_target, cylinder_slabs)
        chk = CollisionChecker(task, env=base.with_obstacles(prims))
        q = torch.tensor([p.start, p.goal], dtype=torch.float64)
        v = chk.configs(q)
        for k, end in enumerate(("start", "goal")):
            for key, arr in (
                ("valid", v.valid),
                ("env_free", v.env_free),
                ("self_free", v.self_free),
                ("within_limits", v.pos_ok),
            ):
                out.setdefault(f"{end}_{key}", []).append(bool(arr[k]))
    return {k: np.asarray(v) for k, v in out.items()}
