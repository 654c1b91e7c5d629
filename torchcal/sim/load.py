"""Simulated loads: the payload each row carries and the joint torques a controller would measure there.

The truth is known: the payload per row (:func:`row_payloads`) drives the true model's compliance through the row's
context, and the measured torques are the true static torques the drives hold (the weight's moment of the links and
the payload, with the opposite sign: :mod:`torchcal.data.load`) plus Gaussian noise. A robot description without
link masses (a DH table) gets seeded true masses for the truth (:func:`true_masses`): the description the
calibration reads still has none.
"""

from __future__ import annotations

import torch

from torchcal._bounds import MAX_PAYLOAD_KG, MAX_SIGMA_TORQUE
from torchcal.errors import OptionError
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor
F64 = torch.float64


def check_load_config(cfg) -> None:
    """Refuse load settings that are not masses (negative, non-finite) or a noise that is no standard deviation."""
    levels = tuple(cfg.payload_levels or ())
    for name, value in [("payload", cfg.payload), ("test_payload", cfg.test_payload)] + [
        ("payload_levels", v) for v in levels
    ]:
        if value is not None and not (0.0 <= float(value) <= MAX_PAYLOAD_KG):
            raise OptionError(f"{name} must be a mass in kg, 0 <= m <= {MAX_PAYLOAD_KG:g}, got {value!r}")
    if cfg.payload_levels is not None and not levels:
        raise OptionError("payload_levels needs at least one level (kg)")
    if not 0.0 <= float(cfg.sigma_torque) <= MAX_SIGMA_TORQUE:
        raise OptionError(
            f"sigma_torque must be a standard deviation in N m, 0 <= s <= {MAX_SIGMA_TORQUE:g}, "
            f"got {cfg.sigma_torque!r}"
        )
    if has_load(cfg) and (cfg.stations > 1 or cfg.probes > 1):
        raise OptionError("simulated loads (payload, torques) take one station and one probe")


def has_load(cfg) -> bool:
    """Whether the campaign carries load columns (a payload setting or measured torques)."""
    return bool(cfg.payload) or cfg.test_payload is not None or cfg.payload_levels is not None or cfg.torques


def row_payloads(cfg, n_train: int, n: int) -> Tensor:
    """Each row's payload ``(n,)`` [kg]: the training rows at ``cfg.payload``, the rest at ``cfg.test_payload``
    (default the same), or both cycling over ``cfg.payload_levels`` (the test rows at ``cfg.test_payload`` where it
    is given: a load the training never saw)."""
    if cfg.payload_levels is not None:
        levels = torch.tensor([float(v) for v in cfg.payload_levels], dtype=F64)
        idx = torch.cat([torch.arange(n_train), torch.arange(n - n_train)]) % len(levels)
        out = levels[idx]
        if cfg.test_payload is not None:
            out[n_train:] = float(cfg.test_payload)
        return out
    test = cfg.payload if cfg.test_payload is None else cfg.test_payload
    out = torch.full((n,), float(test), dtype=F64)
    out[:n_train] = float(cfg.payload)
    return out


def true_masses(robot: RobotModel, g: torch.Generator) -> dict:
    """Give ``robot`` (the true one) seeded link masses where its description has none: 1 to 5 kg per link,
    centres of mass 0.1 m per axis in each link's frame. Returns truth.json's entry."""
    if robot.has_masses:
        return {"from": "the robot description"}
    m = 1.0 + 4.0 * torch.rand(robot.n_joints, generator=g, dtype=F64)
    c = torch.randn(robot.n_joints, 3, generator=g, dtype=F64) * 0.1
    with torch.no_grad():
        robot.masses.copy_(m)
        robot.coms.copy_(c)
    robot.has_masses = True
    return {"from": "seeded (the description has none)", "masses_kg": m.tolist(), "coms_m": c.tolist()}


def measured_torques(robot: RobotModel, q: Tensor, payload: Tensor, sigma: float, g: torch.Generator) -> Tensor:
    """The torques the drives hold at the true joints ``q`` ``(N, dof)`` with ``payload`` ``(N,)`` [kg] at the
    probe, plus noise of ``sigma`` [N m] ``(N, dof)``: ``-gravity_torques + e``."""
    with torch.no_grad():
        tau = -robot.gravity_torques(q, payload)
    return tau + torch.randn(tau.shape, generator=g, dtype=F64) * sigma


def load_columns(payload: Tensor | None, tau: Tensor | None, rows: slice) -> dict[str, Tensor]:
    """The extra columns of the rows ``rows``: ``payload`` and ``tau1..tauN`` where given."""
    out = {} if payload is None else {"payload": payload[rows].clone()}
    if tau is not None:
        out.update({f"tau{k + 1}": tau[rows, k].clone() for k in range(tau.shape[1])})
    return out
