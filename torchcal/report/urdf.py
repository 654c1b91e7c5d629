"""What the calibrated URDF carries and leaves out: the geometry, the lever arm and the tracker pose, not the
non-geometric effects; how far its forward kinematics is from the full model, in its header and in report.md."""

from __future__ import annotations

import torch

from torchcal.effects.base import Context
from torchcal.effects.model import MeasurementModel
from torchcal.robot import transforms as tf
from torchcal.use.export import left_out

Tensor = torch.Tensor


def urdf_gap(model: MeasurementModel, ctx: Context) -> dict:
    """How far the geometry-only part of ``model`` (what a URDF carries) is from the full model on ``ctx``'s poses.

    Returns:
        ``{"n_poses", "rms_mm", "max_mm", "left_out": [labels]}``: distances between the full model's
        prediction and the geometry-only FK (same geometry, lever arm and tracker pose) in the tracker frame.
    """
    model = model
    with torch.no_grad():
        full = model(ctx)
        geo = MeasurementModel(model.robot, [])(ctx)
    d = (full - geo).norm(dim=-1)
    return {
        "n_poses": int(d.shape[0]),
        "rms_mm": float(d.square().mean().sqrt()) * 1e3 if len(d) else 0.0,
        "max_mm": float(d.max()) * 1e3 if len(d) else 0.0,
        "left_out": left_out(model),
    }


def urdf_fk_difference(path, model: MeasurementModel, ctx: Context) -> dict:
    """RMS and max difference between FK of a written URDF (base link to its ``probe`` frame, placed in the
    tracker frame with the model's ``T_tracker_base``) and the full model's prediction ``(N, 3)`` on ``ctx``.

    The URDF is read back with :func:`torchcal.robot.load_robot` (float64), so this measures the file itself, not
    the model it was written from; from its XML elements (``reader="elements"``, the numbers yourdfpy reads, without
    importing yourdfpy's mesh library: this check runs after every calibration).
    """
    from torchcal.robot import load_robot

    model = model
    urdf = load_robot(path, base_link=model.robot.base_link, tip_link="probe", reader="elements").to(model.robot.device)
    with torch.no_grad():
        p_base = urdf(ctx.q)[..., :3, 3]
        p = tf.transform_points(model.robot.T_tracker_base(), p_base)
        d = (model(ctx) - p).norm(dim=-1)
    return {
        "n_poses": int(d.shape[0]),
        "rms_mm": float(d.square().mean().sqrt()) * 1e3,
        "max_mm": float(d.max()) * 1e3,
        "left_out": left_out(model),
    }


def urdf_notes(gap: dict) -> list[str]:
    """Header lines for the calibrated URDF: what it leaves out and what that costs on the training poses."""
    if not gap["left_out"]:
        return ["The calibration found no effect beyond geometry: this URDF carries the whole calibrated model."]
    return [
        f"NOT in this URDF: {', '.join(gap['left_out'])} (non-geometric effects a URDF cannot express).",
        f"On the {gap['n_poses']} training poses, FK of this URDF differs from the full calibrated model by "
        f"RMS {gap['rms_mm']:.4f} mm, max {gap['max_mm']:.4f} mm.",
        "To reach targets with the full model, command the joints from 'torchcal compensate RUN TARGETS.csv'.",
    ]


def urdf_markdown(gap: dict) -> str:
    """A report.md section on what ``robot_calibrated.urdf`` carries and leaves out."""
    lines = ["", "## The calibrated URDF", ""]
    if not gap["left_out"]:
        lines.append(
            "`robot_calibrated.urdf` carries the whole calibrated model (geometry, lever arm as the "
            "`probe` frame, tracker pose as the `tracker` frame): the run found no other effect."
        )
    else:
        lines += [
            f"`robot_calibrated.urdf` carries the geometry, the lever arm (`probe` frame) and the tracker pose "
            f"(`tracker` frame). It leaves out: {', '.join(gap['left_out'])}.",
            "",
            f"On the {gap['n_poses']} training poses its forward kinematics differs from the full model's "
            f"prediction by RMS {gap['rms_mm']:.4f} mm, max {gap['max_mm']:.4f} mm. To use the full model on the "
            "robot, compensate the joint commands: `torchcal compensate RUN TARGETS.csv --out JOINTS.csv`.",
        ]
    return "\n".join(lines) + "\n"
