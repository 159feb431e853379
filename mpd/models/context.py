"""Context encoders: (q_start, q_goal) or (q_start, end-effector goal pose) -> one embedding vector.

As in the authors' networks: one MLP on the joint-space part (q_start, plus q_goal for joint-goal tasks), one
on the end-effector goal pose (position 3 + flattened rotation 9, EE-goal tasks only), and a combining MLP on
the concatenation of their outputs. Each MLP is the authors' ``MLP(n_layers)``: an input layer and ``n_layers``
more hidden layers, i.e. ``n_layers + 1`` hidden ReLU layers of width ``context_dim``, then a linear output of size
``context_dim``. The per-part MLPs take ``context_layers`` (1 for the 2-D tasks and Planar2Link, 2 for the others,
as in the authors' training launcher); the combining MLP takes 1 (two hidden layers), as the authors' default.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from mpd.tasks.spec import CONTEXT_INITS

JOINT_GOAL = "goal_joint_position"
EE_GOAL = "goal_ee_pose"
CONTEXT_KINDS = (JOINT_GOAL, EE_GOAL)

# fields that are NOT min/max normalized (a rotation matrix is already in [-1, 1])
UNNORMALIZED_KEYS = frozenset({"ee_rot"})


def context_keys(kind: str) -> tuple[str, ...]:
    """The fields of a context of this kind (the keys of the dict the encoder consumes)."""
    if kind == JOINT_GOAL:
        return ("q_start", "q_goal")
    if kind == EE_GOAL:
        return ("q_start", "ee_pos", "ee_rot")
    raise ValueError(f"unknown context kind {kind!r} (known: {', '.join(CONTEXT_KINDS)})")


def context_kind_of(keys: set[str] | frozenset[str]) -> str:
    """Infer the context kind from the set of field names."""
    for kind in CONTEXT_KINDS:
        if set(keys) == set(context_keys(kind)):
            return kind
    raise ValueError(
        f"context fields {sorted(keys)} match no context kind (expected {list(context_keys(JOINT_GOAL))} "
        f"or {list(context_keys(EE_GOAL))})"
    )


def context_shapes(kind: str, dof: int) -> dict[str, tuple[int, ...]]:
    """Per-sample shape of each field."""
    if kind == JOINT_GOAL:
        return {"q_start": (dof,), "q_goal": (dof,)}
    context_keys(kind)
    return {"q_start": (dof,), "ee_pos": (3,), "ee_rot": (3, 3)}


def mlp(in_dim: int, out_dim: int, n_layers: int, hidden_dim: int | None = None) -> nn.Sequential:
    """``Linear(in, h), ReLU, n_layers x [Linear(h, h), ReLU], Linear(h, out)``: ``n_layers + 1`` hidden layers of
    width ``hidden_dim`` (default ``out_dim``), the layer count of the authors' ``MLP(n_layers=...)``."""
    if n_layers < 0:
        raise ValueError(f"context_layers must be >= 0, got {n_layers}")
    h = out_dim if hidden_dim is None else hidden_dim
    layers: list[nn.Module] = [nn.Linear(in_dim, h), nn.ReLU()]
    for _ in range(n_layers):
        layers += [nn.Linear(h, h), nn.ReLU()]
    layers.append(nn.Linear(h, out_dim))
    return nn.Sequential(*layers)


class ContextEncoder(nn.Module):
    """Normalized context dict -> ``(B, context_dim)``."""

    def __init__(self, kind: str, dof: int, context_dim: int, n_layers: int = 1, init: str = "default"):
        super().__init__()
        if init not in CONTEXT_INITS:
            raise ValueError(f"model.context_init must be one of {', '.join(map(repr, CONTEXT_INITS))}, got {init!r}")
        self.kind = kind
        self.dof = dof
        self.keys = context_keys(kind)
        self.shapes = context_shapes(kind, dof)
        self.out_dim = context_dim
        if kind == JOINT_GOAL:
            self.joints = mlp(2 * dof, context_dim, n_layers)
            self.ee_pose = None
            combined_in = context_dim
        else:
            self.joints = mlp(dof, context_dim, n_layers)
            self.ee_pose = mlp(3 + 9, context_dim, n_layers)
            combined_in = 2 * context_dim
        self.combine = mlp(combined_in, context_dim, 1)
        if init in ("he", "he-zero"):  # ModelSpec.context_init
            for layer in self.modules():
                if isinstance(layer, nn.Linear):
                    nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
                    nn.init.zeros_(layer.bias)
        if init == "he-zero":  # the embedding starts at 0: the U-Net's FiLM layers see no context until it is learned
            nn.init.zeros_(self.combine[-1].weight)

    def check(self, context: Mapping[str, torch.Tensor]) -> int:
        """Validate fields and shapes; return the batch size."""
        missing = [k for k in self.keys if k not in context]
        if missing:
            raise ValueError(f"context is missing {missing} (a {self.kind} context needs {list(self.keys)})")
        batch = None
        for k in self.keys:
            shape = tuple(context[k].shape)
            if shape[1:] != self.shapes[k] or len(shape) != len(self.shapes[k]) + 1:
                raise ValueError(
                    f"context[{k!r}] must have shape (B, {', '.join(map(str, self.shapes[k]))}), got {shape}"
                )
            if batch is not None and shape[0] != batch:
                raise ValueError(f"context fields have different batch sizes: {batch} and {shape[0]}")
            batch = shape[0]
        return int(batch)

    def forward(self, context: Mapping[str, torch.Tensor]) -> torch.Tensor:
        self.check(context)
        if self.ee_pose is None:
            return self.combine(self.joints(torch.cat([context["q_start"], context["q_goal"]], dim=-1)))
        pose = torch.cat([context["ee_pos"], context["ee_rot"].flatten(1)], dim=-1)
        return self.combine(torch.cat([self.joints(context["q_start"]), self.ee_pose(pose)], dim=-1))
