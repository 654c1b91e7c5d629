"""The load conditions a run was fitted in, and the rows that lie outside them.

A calibration records the range of the payload [kg] and of each measured joint torque [N m] its rows covered
(``model.json`` ``load``; a file without the columns was measured at 0 kg, with no torques). A row to predict
whose payload or torque lies outside that range is a condition the run never saw:

* its ``extrapolation`` takes the twist [rad] that the load beyond the range gives a joint at the reference
  compliance (below), the same unit as the joints' distance beyond the calibrated region, and the larger of the two
  is written;
* its sigma grows by the probe displacement of that twist: ``d = J(q) (k_ref * dtau)`` with ``dtau`` the payload's
  torque beyond the range (:meth:`~torchcal.robot.RobotModel.payload_torques`, from the description's kinematics,
  no masses needed) or the measured torque's distance beyond its range, ``J`` the probe's joint Jacobian, added in
  quadrature with ``|d|`` on every axis (the direction is not known, so each axis may hold all of it), times the
  run's ``load.sigma_scale`` where a re-stationing at such a load measured how much of it its points bore out
  (:func:`torchcal.use.station.restation`; 1 by default).

The reference compliance ``k_ref`` of a joint is zero where the run's model carries the load at that joint
(a compliance driven by the row's payload or torque, whose parameter uncertainty the sigma already propagates);
elsewhere it is the largest compliance the run fitted, or :data:`DEFAULT_COMPLIANCE` where it fitted none.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.data import Measurements

Tensor = torch.Tensor

#: the compliance [rad/(N m)] assumed for a joint whose load the run cannot tell: 1e-5 is a collaborative arm's
#: harmonic drive (about 1e5 N m/rad); an industrial arm is stiffer, so the sigma it gives is on the safe side
DEFAULT_COMPLIANCE = 1e-5
#: the names of predict's ``conditions`` column, by code
CONDITIONS = ("trained", "load beyond training")


def training_load(m: Measurements) -> dict:
    """``model.json``'s ``load``: the payload range [kg] of the rows (``[0, 0]`` without the column), each torque's
    range [N m] (None without torques) and whether the file had the columns."""
    payload = m.payload
    lo, hi = (0.0, 0.0) if payload is None else (float(payload.min()), float(payload.max()))
    tau = m.tau
    return {
        "payload_kg": [lo, hi],
        "payload_column": payload is not None,
        "tau_Nm": None if tau is None else [[float(a), float(b)] for a, b in zip(tau.min(0).values, tau.max(0).values)],
    }


@dataclass
class LoadConditions:
    """Each row's standing against the run's training load.

    Attributes:
        beyond: ``(N,)`` bool, the rows outside the training range.
        extrapolation: ``(N,)`` [rad] the reference twist of the load beyond the range (0 inside).
        sigma: ``(N, 3)`` [m] the standard deviation it adds (0 inside).
        note: what stderr says, or None where every row lies inside.
    """

    beyond: Tensor
    extrapolation: Tensor
    sigma: Tensor
    note: str | None


def _reference_compliance(model, device: torch.device) -> Tensor:
    """``k_ref (dof,)`` [rad/(N m)] per joint on ``device`` (module docstring)."""
    from torchcal.effects.joint import Compliance, LumpedCompliance, TorqueCompliance

    dof = model.robot.dof
    carried = torch.zeros(dof, dtype=torch.bool, device=device)
    fitted = []
    for e in model.effects:
        load_aware = isinstance(e, (Compliance, TorqueCompliance)) or (isinstance(e, LumpedCompliance) and e.load)
        if load_aware:
            carried[e.j] = True
            fitted.append(abs(float(e.k.detach())))
    k = max(fitted) if fitted else DEFAULT_COMPLIANCE
    return torch.where(carried, 0.0, torch.full((dof,), k, dtype=torch.float64, device=device))


def _beyond(value: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """The signed distance of ``value`` beyond ``[lo, hi]`` (0 inside)."""
    return torch.where(value > hi, value - hi, torch.where(value < lo, value - lo, torch.zeros_like(value)))


def load_conditions(model, meta: dict, data, path: str) -> LoadConditions:
    """The rows of ``data`` (read by predict: :class:`~torchcal.data.Measurements`, or a
    :class:`~torchcal.effects.Context` of poses with their load) against the load ``meta["load"]`` the run was fitted
    in."""
    n, dof = data.q.shape[0], model.robot.dof
    q = data.q.detach().cpu()  # predict asks before its model moves to --device
    f64 = dict(dtype=torch.float64, device=q.device)
    zero = torch.zeros(n, **f64)
    load = meta.get("load") if isinstance(meta.get("load"), dict) else {"payload_kg": [0.0, 0.0], "tau_Nm": None}
    lo, hi = (float(v) for v in load.get("payload_kg", [0.0, 0.0]))
    payload = data.payload if data.payload is not None else zero
    dm = _beyond(payload.cpu(), torch.tensor(lo, **f64), torch.tensor(hi, **f64))
    robot = model.robot
    with torch.no_grad():
        com = None if data.payload_com is None else data.payload_com.cpu()
        dtau = robot.payload_torques(q, dm, com) if bool((dm != 0).any()) else torch.zeros(n, dof, **f64)
    tau_range = load.get("tau_Nm")
    if tau_range is not None and data.tau is not None:
        r = torch.tensor(tau_range, **f64)
        dtau_measured = _beyond(data.tau.cpu(), r[:, 0], r[:, 1])
        dtau = torch.where(dtau_measured.abs() > dtau.abs(), dtau_measured, dtau)
    beyond = (dm != 0) | (dtau.abs() > 0).any(1) if tau_range is not None else dm != 0
    twist = _reference_compliance(model, q.device) * dtau  # (N, dof) [rad]
    with torch.no_grad():
        J = robot.probe_jacobian(q)[1] if bool(beyond.any()) else torch.zeros(n, 3, dof, **f64)
    # a re-stationing measured at such a load says how much of the reference displacement its points bore out
    d = (J @ twist.unsqueeze(-1)).squeeze(-1).norm(dim=1) * float(load.get("sigma_scale", 1.0))  # [m]
    ext = twist.abs().max(1).values if dof else zero
    ext = torch.where(beyond, ext.clamp(min=1e-12), zero)  # a flagged row is never 0, however stiff
    note = None
    if bool(beyond.any()):
        k = int(beyond.sum())
        trained = (
            f"{lo:g} to {hi:g} kg" if load.get("payload_column", True) else "0 kg (its rows had no payload column)"
        )
        note = (
            f"torchcal: warning: {path}: {k} of {n} rows carry a load the run was not fitted at (payload fitted "
            f"{trained}{'' if tau_range is None else ', and the torques its rows measured'}): their extrapolation "
            f"and sigma grow with the load beyond it (up to {float(d.max()) * 1e3:.3g} mm), and the conditions "
            "column names them"
        )
    return LoadConditions(beyond, ext, d[:, None].expand(n, 3).clone(), note)


def with_load_sigma(sigma: Tensor | None, extra: Tensor) -> Tensor | None:
    """``sigma`` (N, 3) [m] with ``extra`` added in quadrature (None stays None)."""
    return None if sigma is None else (sigma.square() + extra.to(sigma).square()).sqrt()


__all__ = ["CONDITIONS", "DEFAULT_COMPLIANCE", "LoadConditions", "load_conditions", "training_load", "with_load_sigma"]


def require_torques(model, data: Measurements, path: str) -> None:
    """Refuse rows without ``tau`` columns for a run whose compliance reads the measured joint torques: it has nothing
    to carry their load by (the effect's own refusal names no file)."""
    from torchcal.effects import TorqueCompliance
    from torchcal.errors import MeasurementFileError

    if data.tau is None and any(isinstance(e, TorqueCompliance) for e in model.effects):
        raise MeasurementFileError(
            path,
            "the run's compliance reads the measured joint torques, and these rows have none",
            hint=f"give the rows the columns tau1..tau{model.robot.dof} (N m; N for a prismatic joint): the torques "
            "their poses hold",
        )
