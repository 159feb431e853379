"""Motion-planning costs with batched analytic gradients (no autograd) and their weighted sum.

``CostFunction(task, parametrization, env, preset="official" | "paper")`` is what the planners call; the
single costs live one per module and register themselves in ``COSTS`` (keys: the fields of ``CostWeights``).
"""

from mpd.costs import acceleration, collision, ee_pose, joint_limits, self_collision, velocity  # noqa: F401
from mpd.costs.base import COSTS, PRESETS, SDF_MODES, Cost, CostInput, CostTerm, phase_weights, register
from mpd.costs.composite import CostFunction, CostResult

__all__ = [
    "COSTS",
    "PRESETS",
    "SDF_MODES",
    "Cost",
    "CostFunction",
    "CostInput",
    "CostResult",
    "CostTerm",
    "phase_weights",
    "register",
]
