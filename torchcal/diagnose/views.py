"""What a decision looks like: the residual against the chosen regressor, before and after.

The residual is a 3-vector per pose; the effect moves the probe along one direction per pose.
Projecting the residual onto that direction gives one number per pose that a plot against the
effect's regressor (gravity torque, loaded flank, joint angle, time, temperature) can show:

* joint effects: the direction ``u_i = J_qj,i / |J_qj,i|`` in which joint j moves the probe;
* drift: the direction of the fitted drift's displacement, signed with the drift variable;
* the instrument's own errors: the direction of the fitted error's displacement.
"""

from __future__ import annotations

import copy

import torch

from torchcal.diagnose.candidates import Candidate
from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.problem import probe_joint_jacobian

Tensor = torch.Tensor


def _without(model: MeasurementModel, index: int) -> MeasurementModel:
    out = copy.deepcopy(model)
    with torch.no_grad():
        for p in out.effects[index].parameters():
            p.zero_()
    return out


def _find(model: MeasurementModel, cand: Candidate) -> int:
    for i, e in enumerate(model.effects):
        if e.kind == cand.kind and e.joint == cand.joint and getattr(e, "variable", None) == cand.variable:
            if e.kind == "coupling" and e.source != cand.source:  # two couplings into one joint: its source tells
                continue
            return i
    raise ValueError(f"the model has no effect {cand.name}")


def residual_view(cand: Candidate, before: MeasurementModel, after: MeasurementModel, ctx: Context, p: Tensor) -> dict:
    """Per-pose regressor and residuals projected on the effect's direction (module docstring) [m].

    Returns:
        ``x`` regressor ``(N,)``, ``xlabel``, ``before`` and ``after`` projected residuals ``(N,)``,
        ``effect`` the fitted effect's displacement along the same direction ``(N,)``.
    """
    idx = _find(after, cand)
    with torch.no_grad():
        pred_after = after(ctx)
        d = pred_after - _without(after, idx)(ctx)  # the effect's share of the prediction (tracker frame)
        e_before, e_after = p - before(ctx), p - pred_after
        if cand.joint is not None:
            u = probe_joint_jacobian(after, ctx)[:, :, cand.joint - 1]
        elif cand.kind == "instrument":  # along the fitted error's own displacement
            u = d
        else:
            dv = after.effects[idx].regressor(after.robot, ctx)
            u = d * torch.sign(dv)[:, None]
        u = u / u.norm(dim=-1, keepdim=True).clamp(min=1e-300)
        x, xlabel = cand.regressor(after.robot, ctx)
    return {
        "x": x,
        "xlabel": xlabel,
        "before": (e_before * u).sum(-1),
        "after": (e_after * u).sum(-1),
        "effect": (d * u).sum(-1),
    }
