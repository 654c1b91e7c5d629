"""Joints a set of poses hardly moved: named at calibrate time, and opened to their limits where a plan
samples candidates for a run (:func:`torchcal.use.plan.candidate_region`). Here, below both, so that planning does
not load the pipeline."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

Tensor = torch.Tensor

#: a revolute joint whose training poses span less than this [deg] is narrow: a few degrees tell the geometry of the
#: joints beyond it only where they move, and nothing of what its own motion would reveal
NARROW_DEG = 5.0
#: a joint (of either kind) whose training range is below this share of its limits (a revolute joint's clipped to a
#: turn) is narrow too: a track that moved 2 cm of its 3 m
NARROW_SHARE = 0.03


@dataclass(frozen=True)
class NarrowJoint:
    """A joint the training poses hardly moved (:func:`narrow_joints`): 1-based ``joint``, its training ``range`` and
    its ``limits`` span in ``unit`` (deg for a revolute joint, m for a prismatic one)."""

    joint: int
    range: float
    limits: float
    unit: str

    def to_dict(self) -> dict:
        return {"joint": self.joint, "range": self.range, "limits": self.limits, "unit": self.unit}

    def text(self) -> str:
        whole = "a turn" if self.unit == "deg" and self.limits >= 360.0 else "its limits"
        share = 100 * self.range / self.limits
        return f"q{self.joint} moved {self.range:.3g} {self.unit} in the training poses ({share:.2g} % of {whole})"


def narrow_joints(q: Tensor, limits: Tensor, joint_types: tuple[str, ...]) -> list[NarrowJoint]:
    """The joints whose training range ``q (N, dof)`` is under :data:`NARROW_DEG` (revolute) or under
    :data:`NARROW_SHARE` of their ``limits (dof, 2)`` span."""
    q, limits = q.detach().cpu(), limits.detach().cpu()
    spread = q.max(dim=0).values - q.min(dim=0).values
    out = []
    for j, kind in enumerate(joint_types):
        span = float(limits[j, 1] - limits[j, 0])
        if kind == "revolute":
            span = min(span, 2 * math.pi)
            small = math.degrees(float(spread[j])) < NARROW_DEG or float(spread[j]) < NARROW_SHARE * span
            scale, unit = 180.0 / math.pi, "deg"
        else:
            small = float(spread[j]) < NARROW_SHARE * span
            scale, unit = 1.0, "m"
        if small:
            out.append(NarrowJoint(j + 1, float(spread[j]) * scale, span * scale, unit))
    return out
