"""Task files: schema of ``mpd/tasks/data/*.toml`` (or any user file with the same layout)."""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from mpd.schema import ConfigError

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


@dataclass(frozen=True)
class ObjectSpec:
    """A sphere (centre, radius) or a box (centre, full side lengths ``size``, optional rotation)."""

    type: Literal["sphere", "box"]
    centre: list[float]
    radius: float | None = None
    size: list[float] | None = None
    orientation_wxyz: tuple[float, float, float, float] | None = None
    name: str = ""

    def validate(self) -> None:
        if self.type == "sphere":
            if self.radius is None or self.radius <= 0:
                raise ConfigError(None, "radius", f"a sphere needs a positive radius, got {self.radius}")
            if self.size is not None or self.orientation_wxyz is not None:
                raise ValueError("a sphere takes no size or orientation_wxyz")
        else:
            if self.size is None or len(self.size) != len(self.centre) or min(self.size) <= 0:
                n = len(self.centre)
                raise ConfigError(None, "size", f"a box needs {n} positive side lengths, got {self.size}")
            if self.radius is not None:
                raise ValueError("a box takes no radius")
            if self.orientation_wxyz is not None:
                if len(self.centre) != 3:
                    raise ValueError("orientation_wxyz is for 3-D boxes")
                if abs(np.linalg.norm(self.orientation_wxyz) - 1) > 1e-6:
                    q = list(self.orientation_wxyz)
                    raise ConfigError(None, "orientation_wxyz", f"{q} is not a unit quaternion")


@dataclass(frozen=True)
class EnvironmentSpec:
    dim: Literal[2, 3]
    workspace: tuple[list[float], list[float]]
    obstacles: list[ObjectSpec]
    extra_objects: list[ObjectSpec] = field(default_factory=list)
    sdf_cell_size: float = 0.005
    box_corner_radius: float = 0.0

    def validate(self) -> None:
        lo, hi = self.workspace
        if len(lo) != self.dim or len(hi) != self.dim or any(a >= b for a, b in zip(lo, hi)):
            shape = f"[[{self.dim} lows], [{self.dim} highs]]"
            raise ConfigError(None, "workspace", f"must be {shape} with low < high, got {[lo, hi]}")
        for key in ("obstacles", "extra_objects"):
            for i, o in enumerate(getattr(self, key)):
                if len(o.centre) != self.dim:
                    n = len(o.centre)
                    raise ConfigError(
                        None, f"{key}[{i}].centre", f"has {n} coordinates, the environment is {self.dim}-D"
                    )
        if self.sdf_cell_size <= 0:
            raise ConfigError(None, "sdf_cell_size", f"must be positive, got {self.sdf_cell_size}")


@dataclass(frozen=True)
class RobotRef:
    name: str


@dataclass(frozen=True)
class PoseRegionSpec:
    """End-effector poses: x, y, z and Euler angles (scipy 'xyz', degrees) uniform in one of their intervals."""

    name: str
    x: list[tuple[float, float]]
    y: list[tuple[float, float]]
    z: list[tuple[float, float]]
    rot_x_deg: list[tuple[float, float]]
    rot_y_deg: list[tuple[float, float]]
    rot_z_deg: list[tuple[float, float]]
    rotation_base: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


@dataclass(frozen=True)
class ContextSpec:
    kind: Literal["goal_joint_position", "goal_ee_pose"]
    min_start_goal_distance: float = 0.0
    pose_regions: list[PoseRegionSpec] = field(default_factory=list)
    region_pair_probability: float = 0.5


@dataclass(frozen=True)
class TrajectorySpec:
    duration: float
    n_control_points: int
    n_points: int = 128
    bspline_degree: int = 5
    n_waypoints: int | None = None  # waypoint ablation; defaults to n_control_points (the paper's choice)

    def validate(self) -> None:
        if self.duration <= 0:
            raise ValueError("trajectory.duration must be positive")
        if self.n_control_points < self.bspline_degree + 1 or self.n_control_points < 7:
            raise ValueError(
                f"trajectory.n_control_points must be at least max(degree + 1, 7), got {self.n_control_points}"
            )
        if self.n_points < 2:
            raise ValueError("trajectory.n_points must be at least 2")


@dataclass(frozen=True)
class CollisionSpec:
    cost_margin: float
    clearance: float = 0.0
    validity_margin: float = 0.0
    self_collision: bool = False


@dataclass(frozen=True)
class CostWeights:
    collision: float = 0.0
    self_collision: float = 0.0
    joint_limits: float = 0.0
    ee_pose: float = 0.0
    velocity: float = 0.0
    acceleration: float = 0.0


@dataclass(frozen=True)
class CostsSpec:
    weights: CostWeights
    paper_weights: CostWeights | None = None


@dataclass(frozen=True)
class InferenceSpec:
    """Task-specific overrides of the planner presets (see mpd.planners.presets)."""

    guide_fraction: float = 0.3


# initializations of the context MLPs (ModelSpec.context_init); "default" is PyTorch's, the authors'
CONTEXT_INITS = ("default", "he", "he-zero")


@dataclass(frozen=True)
class ModelSpec:
    unet_dim: int = 32
    unet_dim_mults: list[int] = field(default_factory=lambda: [1, 2, 4])
    context_dim: int = 32
    context_layers: int = 1
    time_emb_dim: int = 32
    # 0 (the paper): the U-Net alone. > 0: a "goal head" beside it, an MLP of this width (mpd.models.diffusion.
    # GoalHead) whose output is added to the predicted noise of the last row, from that row's noisy values, the step
    # and the context embedding: end-effector-goal tasks only, where the last row is the free final configuration,
    # a learned inverse kinematics that the U-Net learns slowly (reports/recipe-study-panda). A study option of the
    # `cpu` profiles; the diffusion models only (the CVAE ignores it).
    goal_head_width: int = 0
    # initialization of the context MLPs' linear layers: "default" is PyTorch's (the authors'), under which the
    # context embedding's spread over contexts at initialization is ~0.002 after the MLPs' six ReLU layers (vs ~0.04
    # mean magnitude), so a short training hardly sees the goal (reports/recipe-study-panda); "he": He / Kaiming
    # normal weights (fan-in, ReLU gain) and zero biases, a spread of ~0.5; "he-zero": the same with the output layer
    # of the combining MLP at zero, so the embedding starts at 0 while the hidden layers carry the context (He alone
    # stalled the U-Net's training, reports/recipe-study-panda-goal). Diffusion models only (the CVAE ignores it); a
    # study option of the `cpu` profiles.
    context_init: Literal["default", "he", "he-zero"] = "default"


@dataclass(frozen=True)
class ModelOverride:
    """The network of a training profile where it differs from the task's ``[model]`` (the paper's sizes): only the
    fields given change, e.g. ``[model_profiles.cpu] unet_dim = 16`` (a network that trains within a CPU budget and
    ships under the size limit of the shipped priors). A model's identity is its resolved ModelSpec: a profile
    without an override keeps its models' identities."""

    unet_dim: int | None = None
    unet_dim_mults: list[int] | None = None
    context_dim: int | None = None
    context_layers: int | None = None
    time_emb_dim: int | None = None
    goal_head_width: int | None = None
    context_init: Literal["default", "he", "he-zero"] | None = None

    def changes(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}


@dataclass(frozen=True)
class TrainingSpec:
    batch_size: int
    steps: int
    lr: float = 3e-4
    # "constant" (the paper and the authors) or "cosine": linear warm-up, then cosine decay to lr_min_ratio * lr, which
    # gets a much lower loss out of the short CPU budgets of the `cpu` profiles; or "wsd" (warm-up, stable, decay):
    # constant after the warm-up, then a cosine decay to lr_min_ratio * lr over the last decay_fraction of the steps.
    # The stable part of a wsd run does not depend on `steps`, so a longer budget resumes from the stable-phase
    # snapshot of a shorter one (mpd.models.train: "trunks"), which makes a learning curve cost about one training.
    lr_schedule: Literal["constant", "cosine", "wsd"] = "constant"
    warmup_steps: int = 0
    lr_min_ratio: float = 0.1
    decay_fraction: float = 0.2
    weight_decay: float = 0.01
    grad_clip_norm: float = 1.0
    ema_decay: float = 0.995
    ema_start: int = 1000
    ema_every: int = 10
    val_every: int = 1000
    checkpoint_every: int = 5000
    # diffusion loss weighting over the noise levels: "uniform" (the paper) or "min_snr" (Hang et al. 2023:
    # w_t = min(SNR_t, min_snr_gamma) / SNR_t for the epsilon loss, which stops the nearly clean levels dominating)
    loss_weighting: Literal["uniform", "min_snr"] = "uniform"
    min_snr_gamma: float = 5.0
    # diffusion steps the training draws: "uniform" over 0..N-1 (the paper), or "sampler": with probability
    # t_grid_fraction a step of the 15-step quadratic DDIM grid the planners sample on (mpd.models.diffusion.
    # sampler_grid), else uniform; a short CPU training then spends most of its samples on the levels it is used at
    t_sampling: Literal["uniform", "sampler"] = "uniform"
    t_grid_fraction: float = 0.8
    # arithmetic of the training forward and backward passes: "fp32", or "bf16" autocast (weights, optimizer, EMA and
    # the validation loss stay float32) where the device computes bf16 natively (AVX-512 BF16, AMX, a GPU); on a CPU
    # without (e.g. AVX2 only) a bf16 training runs in fp32 arithmetic, because emulated bf16 is ~30x slower
    # (mpd.device.training_arithmetic; the model's meta records "arithmetic"). The same setting gives the same model
    # identity everywhere: bit-identical on the same CPU type and torch thread count, statistically equivalent
    # elsewhere (bf16 and fp32 trainings of equal steps sample alike: reports/recipe-study-2d).
    precision: Literal["fp32", "bf16"] = "fp32"
    # weight of the model's last row in the diffusion loss, relative to 1 for every other row (a weighted mean over
    # rows). With an end-effector goal that row is the free final configuration (the B-spline's last free control
    # point, or the last waypoint), the only row that must be read off the goal pose: 1 is the paper; > 1 is a
    # study option of the `cpu` profiles for the Panda, whose short trainings do not learn the goal
    # (reports/recipe-study-panda). Joint-goal tasks fix their last rows, so there it must stay 1.
    goal_row_weight: float = 1.0
    # CVAE only: the KL term's weight rises linearly from 0 to beta over this many steps (Bowman et al. 2016), 0: beta
    # from the first step (the authors). A remedy for posterior collapse, the decoder ignoring its latent, which a
    # cpu-profile CVAE of EnvSpheres3D showed (reports/eval-panda-cpu); a diffusion model's identity never carries it.
    kl_warmup_steps: int = 0
    # train on the dataset's training contexts whose start and goal are at least this far apart in joint space (the
    # norm of q_goal - q_start; joint-space goals only); 0: all of them (the paper). The evaluations draw only
    # contexts at least the task's `context.min_start_goal_distance` apart, ~30 % of the point-mass data, and the
    # `cpu` priors fit those long motions worst (reports/prior-misses-2d): a study option of the CPU budgets. The
    # normalization and the validation loss keep every context.
    min_start_goal_distance: float = 0.0


@dataclass(frozen=True)
class DataSpec:
    planner_time_limit: float = 10.0
    paper_n_contexts: int = 10000


@dataclass(frozen=True)
class TaskSpec:
    schema_version: int
    name: str
    environment: EnvironmentSpec
    robot: RobotRef
    context: ContextSpec
    trajectory: TrajectorySpec
    collision: CollisionSpec
    costs: CostsSpec
    description: str = ""
    inference: InferenceSpec = field(default_factory=InferenceSpec)
    model: ModelSpec = field(default_factory=ModelSpec)
    training: dict[str, TrainingSpec] = field(default_factory=dict)
    # per training profile, the network's sizes where they differ from [model] (Task.model(profile))
    model_profiles: dict[str, ModelOverride] = field(default_factory=dict)
    data: DataSpec = field(default_factory=DataSpec)

    def validate(self) -> None:
        if self.schema_version != 1:
            raise ValueError(f"schema_version {self.schema_version} is not supported (this mpd reads 1)")
        if not _NAME.fullmatch(self.name):
            # the name is the task's identity in results, figure and recording file names and cache folders
            raise ValueError(
                f"name {self.name!r}: use letters, digits, '-', '_' and '.' only, starting with a letter or digit"
            )
        if self.context.kind == "goal_ee_pose" and self.costs.weights.ee_pose <= 0:
            raise ValueError("costs.weights.ee_pose must be positive for an end-effector-goal task")
        for profile, override in self.model_profiles.items():
            where = f"model_profiles.{profile}"
            if profile not in self.training:
                have = ", ".join(self.training) or "none"
                raise ConfigError(None, where, f"no training profile {profile!r} (this task has: {have})")
            if not override.changes():
                raise ConfigError(None, where, "empty: give the network sizes that differ from [model]")
            for name, v in override.changes().items():
                if name == "context_init":
                    if v not in CONTEXT_INITS:
                        raise ConfigError(None, f"{where}.{name}", f"must be one of {CONTEXT_INITS}, got {v!r}")
                    continue
                if any(x < 1 for x in (v if isinstance(v, list) else [v])) or v == []:
                    raise ConfigError(None, f"{where}.{name}", f"must be positive, got {v!r}")
