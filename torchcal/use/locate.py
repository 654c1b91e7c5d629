"""The instrument's rough pose before any calibration: a few points measured at poses of the nominal robot.

``plan`` needs to know where the tracker stands (to keep the poses whose reflector it sees) before the campaign that
would calibrate it exists. Three or more points measured at known joints fix it: the nominal model places the probe
in the base frame, and the rigid transform of those positions onto the measured ones is the tracker's pose. With four
or more points whose tool orientations differ, the lever arm is fitted too (about its nominal value, under a prior),
which removes most of what a wrong nominal lever arm costs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.errors import EstimationError
from torchcal.estimate.rigid import fit_instrument_and_tool

Tensor = torch.Tensor

#: the lever arm on the flange when nothing says which [m] (the simulator's nominal and ``plan``'s default)
NOMINAL_LEVER = (0.0, 0.0, 0.1)
#: how far the true lever arm may lie from the nominal one [m] (the prior's sigma when it is fitted)
LEVER_PRIOR_M = 0.05
#: what the nominal robot misses by before a calibration [m]: the scale of the residuals the prior is weighed against
NOMINAL_MISS_M = 1e-3
#: the least spread of tool orientations [rad] over the points for the lever arm to be fitted: a tool that hardly
#: turns cannot tell a lever arm from the instrument's position
MIN_TURN_RAD = math.radians(10.0)


@dataclass(frozen=True)
class Located:
    """The instrument's pose found by :func:`locate`.

    Attributes:
        T_tracker_base: ``(4, 4)`` the robot base in the instrument frame.
        lever: ``(3,)`` the probe on the flange [m], fitted or as given.
        lever_fitted: whether the points fixed the lever arm (four or more, tool orientations spread).
        rms: RMS distance [m] of the measured points from the located model's.
        n: the points used.
    """

    T_tracker_base: Tensor
    lever: Tensor
    lever_fitted: bool
    rms: float
    n: int

    def tracker_in_base(self) -> Tensor:
        """The instrument's position in the robot's base frame ``(3,)`` [m] (what ``plan --tracker`` takes)."""
        R, t = self.T_tracker_base[:3, :3], self.T_tracker_base[:3, 3]
        return -R.T @ t

    def to_dict(self) -> dict:
        return {
            "tracker_in_base_mm": [float(v) * 1e3 for v in self.tracker_in_base()],
            "T_tracker_base": self.T_tracker_base.tolist(),
            "lever_mm": [float(v) * 1e3 for v in self.lever],
            "lever_fitted": self.lever_fitted,
            "rms_mm": self.rms * 1e3,
            "n_points": self.n,
        }


def tool_turn(T_base_flange: Tensor) -> float:
    """The largest angle [rad] between two of the poses' tool (flange z) axes."""
    z = T_base_flange[:, :3, 2]
    return float(torch.acos((z @ z.T).clamp(-1.0, 1.0)).max())


def locate(robot, q: Tensor, p: Tensor, lever: Tensor | None = None, fit_lever: bool | None = None) -> Located:
    """The instrument's pose from points ``p (N, 3)`` [m] measured at joints ``q (N, dof)`` of the nominal ``robot``.

    Args:
        lever: the probe on the flange [m] (default :data:`NOMINAL_LEVER`): held with three points, or where the tool
            hardly turned; the prior's centre where it is fitted.
        fit_lever: fit the lever arm (default: where four or more points turn the tool by :data:`MIN_TURN_RAD`).

    Raises:
        EstimationError: fewer than three points, points that do not fix a rotation, or ``fit_lever=True`` on points
            that cannot fix a lever arm.
    """
    n = int(q.shape[0])
    if n < 3:
        raise EstimationError(f"the instrument's pose needs three or more points measured at known joints, got {n}")
    dt = torch.float64
    with torch.no_grad():
        T = robot(q.to(device=robot.device, dtype=dt)).cpu()
    p = p.detach().to(device="cpu", dtype=dt)
    centre = (
        torch.tensor(NOMINAL_LEVER, dtype=dt, device="cpu")
        if lever is None
        else lever.detach().to(device="cpu", dtype=dt)
    )
    can = n >= 4 and tool_turn(T) >= MIN_TURN_RAD
    if fit_lever and not can:
        raise EstimationError(
            f"the lever arm needs four or more points whose tool orientations differ by "
            f"{math.degrees(MIN_TURN_RAD):.0f} deg or more; these {n} turn it by {math.degrees(tool_turn(T)):.1f} deg"
        )
    fit = can if fit_lever is None else bool(fit_lever)
    if fit:
        ratio = (NOMINAL_MISS_M / LEVER_PRIOR_M) ** 2
        T_tb, t, rms = fit_instrument_and_tool(T, p, centre, lever_prior=(centre, ratio))
    else:
        T_tb, t, rms = fit_instrument_and_tool(T, p, centre, iterations=0)
    return Located(T_tb, t if fit else centre, fit, rms, n)
