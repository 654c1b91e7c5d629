"""Which rows lie where a run never was: a joint beyond the range it covered (or moved from where the calibration held
it), or a tool axis turned further over than any calibration pose; with the words that say so."""

from __future__ import annotations

import math

import torch

from torchcal._bounds import SIGMA_JOINT

#: how far beyond the calibrated region a reading must lie to be warned about, in joint reading noises (the default
#: ``sigma_joint``, 0.0005 deg: 1.7e-4 rad or m): a pose 2.5e-7 rad beyond, or compensate's own solution 2-6e-5 rad
#: beyond a training pose, is the same pose within the readings' noise
OUTSIDE_TOL_SIGMAS = 20.0


def outside_rows(model, q) -> list[tuple[int, str]]:
    """The rows of ``q (N, dof)`` worth a warning, with why: a joint beyond the range it covered in the calibration
    by more than the tolerance (:data:`OUTSIDE_TOL_SIGMAS`), or a joint the calibration held still (a range within
    the tolerance) moved away from where it was held."""
    from torchcal.use.rundir import tool_axis_beyond

    turned = tool_axis_beyond(model, q) if getattr(model, "tool_cone", None) is not None else None
    if model.region is None and turned is None:
        return []
    if model.region is None:
        return [(i, _turned_why(float(turned[i]))) for i in range(len(q)) if float(turned[i]) > TURNED_TOL]
    tol = OUTSIDE_TOL_SIGMAS * SIGMA_JOINT
    lo, hi = (x.detach().cpu() for x in model.region)
    beyond = torch.maximum(lo - q.detach().cpu(), q.detach().cpu() - hi).clamp(min=0)  # (N, dof)
    held = (hi - lo) <= tol
    out = []
    for i in range(beyond.shape[0]):
        far = [k for k in range(beyond.shape[1]) if float(beyond[i, k]) > tol]
        if not far:
            if turned is not None and float(turned[i]) > TURNED_TOL:
                out.append((i, _turned_why(float(turned[i]))))
            continue
        k = max(far, key=lambda j: float(beyond[i, j]))
        unit = "m" if model.robot.joint_types[k] == "prismatic" else "rad"
        if bool(held[k]):
            why = (
                f"q{k + 1} moved {float(beyond[i, k]):.3g} {unit} from where the calibration held it (it never moved "
                "there)"
            )
        else:
            why = f"the pose lies {float(beyond[i, k]):.3g} {unit} beyond the calibrated region (q{k + 1})"
        out.append((i, why))
    return out


#: how far [rad] a tool axis must lie beyond the cone the calibration's tool axes covered to be warned about (0.1 deg)
TURNED_TOL = math.radians(0.1)


def _turned_why(angle: float) -> str:
    return (
        f"the tool axis lies {math.degrees(angle):.3g} deg beyond the orientations the calibration saw (a tool turned "
        "further over than any calibration pose)"
    )
