"""Campaigns with effects written as plain formulas, outside the effect library's families.

:mod:`torchcal.sim.campaign` injects the effect modules the calibration fits, so a test built on it
can only find what the library already knows. This generator writes its effects as formulas on
tensors, not as :mod:`torchcal.effects` modules, in forms the library need not have:

* ``harmonic``: ``dq_j = A sin(k q_j + phi)`` of any order ``k`` (3 to 8 and beyond) on any joint;
* ``polynomial``: ``dq_j = sum_d c_d q_j^d`` (degree 1: a transmission-ratio error);
* ``joint_time``: a joint error that changes over the campaign, ``dq_j = A s(t) sin(k q_j + phi)`` with
  ``s = (t - t_0) / duration`` growing from 0 to 1 (order ``k = 0``: ``sin`` replaced by 1, a joint offset
  that drifts linearly); a product of a joint angle and time that neither shows alone;
* ``warmup``: the tracker-frame position moves by ``A u (1 - exp(-(t - t_0) / tau))`` along a unit
  vector ``u`` (an axis index, ``"horizontal"`` for a random horizontal direction, or a vector), with
  the time constant ``tau`` [s];

and any combination of them. Each effect is scaled so that the RMS probe displacement it causes alone
over all poses equals its ``size`` [m]. Geometry bias, tracker placement, lever arm, poses and noise
are those of :func:`torchcal.sim.campaign.simulate` (same :class:`SimConfig`); static test poses are
interleaved in time with the training poses (a seeded random draw), trajectories are split as there.
The result is a :class:`~torchcal.sim.campaign.Campaign` whose ``model`` holds the true geometry
without the effects (their formulas are in ``truth["effects"]``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import torch

from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.robot import transforms as tf
from torchcal.sim.campaign import Campaign, SimConfig, _config_dict, _measured, _true_robot
from torchcal.sim.poses import Scene, random_poses, trajectory

Tensor = torch.Tensor
F64 = torch.float64

FORMS = ("harmonic", "polynomial", "warmup", "joint_time")


@dataclass
class OutsideEffect:
    """One effect as a formula (module docstring).

    Attributes:
        form: ``harmonic``, ``polynomial``, ``warmup`` or ``joint_time``.
        joint: 1-based joint (harmonic, polynomial, joint_time).
        order: harmonic order k (joint_time: 0 for an offset drifting in time; default 0).
        coeffs: polynomial shape ``c_1..c_D`` (rescaled to ``size``); default ``(1.0,)``.
        axis: warmup direction: 0, 1, 2 (tracker x, y, z), ``"horizontal"`` or a 3-vector.
        tau: warmup time constant [s]; None draws one uniformly in 5-60 min.
        size: RMS probe displacement [m].
        phase: harmonic phase [rad]; None draws one.
    """

    form: str
    joint: int | None = None
    order: int | None = None
    coeffs: tuple[float, ...] | None = None
    axis: int | str | tuple[float, float, float] | None = None
    tau: float | None = None
    size: float = 4e-5
    phase: float | None = None

    def __post_init__(self):
        if self.form not in FORMS:
            raise OptionError(f"outside effect form '{self.form}' is not one of {FORMS}")
        if self.form in ("harmonic", "polynomial", "joint_time") and self.joint is None:
            raise OptionError(f"a {self.form} effect needs a joint")
        if self.form == "harmonic" and not (self.order and self.order >= 1):
            raise OptionError(f"a harmonic effect needs an order >= 1, got {self.order}")
        if self.form == "joint_time" and not (self.order or 0) >= 0:
            raise OptionError(f"a joint_time effect needs an order >= 0, got {self.order}")
        if self.form == "warmup" and self.axis is None:
            raise OptionError("a warmup effect needs an axis (0, 1, 2, 'horizontal' or a vector)")
        if not self.size > 0:
            raise OptionError(f"effect size must be positive, got {self.size}")


def _joint_term(e: OutsideEffect, q: Tensor, amp: float, phase: float, coeffs: Tensor, s: Tensor) -> Tensor:
    qj = q[:, e.joint - 1]
    if e.form == "harmonic":
        return amp * torch.sin(e.order * qj + phase)
    if e.form == "joint_time":
        return amp * s * (torch.sin(e.order * qj + phase) if e.order else torch.ones_like(qj))
    return amp * (qj[:, None] ** torch.arange(1, len(coeffs) + 1, dtype=F64) @ coeffs)


def simulate_outside(effects: list[OutsideEffect], cfg: SimConfig | None = None) -> Campaign:
    """Simulate a campaign with ``effects`` (module docstring); ``cfg`` gives everything else.

    ``cfg.effects`` is ignored (the effects here are formulas). For static poses ``cfg.test_poses``
    test poses are drawn among all ``cfg.poses + cfg.test_poses`` in time order.
    """
    cfg = replace(cfg or SimConfig(), effects=[])
    g = torch.Generator().manual_seed(int(cfg.seed))
    nominal, robot, T, tracker_in_base, lever_nominal = _true_robot(cfg, g, [(e.form, e.joint) for e in effects])
    scene = Scene(nominal, tracker_in_base, lever_nominal, cfg.sight)
    if cfg.trajectory:
        q = trajectory(scene, cfg.samples, g)
        t = torch.arange(len(q), dtype=F64) * cfg.sample_interval_s
        train_idx, test_idx = torch.arange(cfg.train_samples), torch.arange(cfg.train_samples, len(q))
    else:
        n = cfg.poses + cfg.test_poses
        q = random_poses(scene, n, g)
        t = (
            torch.arange(n, dtype=F64) * cfg.pose_interval_s
            + torch.rand(n, generator=g, dtype=F64) * 0.5 * cfg.pose_interval_s
        )
        perm = torch.randperm(n, generator=g)
        train_idx, test_idx = torch.sort(perm[cfg.test_poses :]).values, torch.sort(perm[: cfg.test_poses]).values
    duration = float(t[-1] - t[0]) if len(t) > 1 else 1.0
    temperature = 20.0 + torch.randn(len(t), generator=g, dtype=F64) * 0.02

    with torch.no_grad():
        p0 = tf.transform_points(T, robot.probe_in_base(q))
    dq = torch.zeros_like(q)
    dp = torch.zeros_like(p0)
    truth_effects = []
    for e in effects:
        rec = {"form": e.form, "size_m": e.size}
        if e.form in ("harmonic", "polynomial", "joint_time"):
            phase = float(torch.rand(1, generator=g, dtype=F64)) * 2 * math.pi if e.phase is None else float(e.phase)
            coeffs = torch.as_tensor(e.coeffs if e.coeffs is not None else (1.0,), dtype=F64)
            shape = _joint_term(e, q, 1.0, phase, coeffs, (t - t[0]) / duration)
            with torch.no_grad():
                dq1 = torch.zeros_like(q)
                dq1[:, e.joint - 1] = shape
                disp = tf.transform_points(T, robot.probe_in_base(q + dq1)) - p0
            amp = e.size / float(disp.norm(dim=-1).square().mean().sqrt())
            term = amp * shape
            dq[:, e.joint - 1] += term
            rec.update(joint=e.joint, variable=f"q{e.joint}" if e.form != "joint_time" else f"q{e.joint}_t")
            if e.form == "joint_time":
                rec.update(order=e.order or 0, amplitude_rad_at_end=amp, phase=phase, variables=[f"q{e.joint}", "t"])
            elif e.form == "harmonic":
                rec.update(
                    order=e.order,
                    amplitude_rad=amp,
                    phase=phase,
                    a_sin=amp * math.cos(phase),
                    b_cos=amp * math.sin(phase),
                )
            else:
                rec.update(degree=len(coeffs), coeffs=(amp * coeffs).tolist())
        else:
            if isinstance(e.axis, str):
                if e.axis != "horizontal":
                    raise OptionError(f"warmup axis '{e.axis}' is not 'horizontal', an index or a vector")
                ang = float(torch.rand(1, generator=g, dtype=F64)) * 2 * math.pi
                u = torch.tensor([math.cos(ang), math.sin(ang), 0.0], dtype=F64)
            elif isinstance(e.axis, int):
                u = torch.zeros(3, dtype=F64)
                u[e.axis] = 1.0
            else:
                u = torch.as_tensor(e.axis, dtype=F64)
                u = u / u.norm()
            tau = float(e.tau) if e.tau is not None else 60.0 * (5 + 55 * float(torch.rand(1, generator=g, dtype=F64)))
            shape = -torch.expm1(-(t - t[0]) / tau)
            amp = e.size / float(shape.square().mean().sqrt())
            dp += amp * shape[:, None] * u
            rec.update(variable="t", axis_tracker=u.tolist(), amplitude_m=amp, tau_s=tau, t0_s=float(t[0]))
        truth_effects.append(rec)

    with torch.no_grad():
        p_true = tf.transform_points(T, robot.probe_in_base(q + dq)) + dp
    for rec, e in zip(truth_effects, effects):
        rec["rms_m"] = e.size  # by construction (joint effects: to first order in the amplitude)
    total = (p_true - p0).norm(dim=-1)
    part = _measured(cfg, g, q, p_true, t, temperature, "torchcal.sim.outside")

    geo = robot.geometry
    truth = {
        "generator": "torchcal.sim.outside",
        "config": _config_dict(cfg),
        "robot": {"spec": str(cfg.robot), "name": robot.name, "dof": robot.dof},
        "geometry": {
            "parametrisation": type(geo).__name__,
            "columns": list(geo.COLUMNS),
            "names": list(geo.names),
            "delta": geo.delta.detach().flatten().tolist(),
        },
        "instrument": {"T_tracker_base": T.tolist(), "tracker_in_base_m": tracker_in_base.tolist()},
        "tool": {"t_flange_probe": robot.tool.nominal.tolist()},
        "noise": {"tracker_sigma_m": cfg.sigma_tracker, "joint_sigma_rad": math.radians(cfg.sigma_joint_deg)},
        "effects": truth_effects,
        "effects_total_rms_m": float(total.square().mean().sqrt()),
        "duration_s": duration,
        "outside_effects": [asdict(e) for e in effects],
        "files": {"train": {"n": len(train_idx)}, "test": {"n": len(test_idx)}},
    }
    model = MeasurementModel(robot, [])
    return Campaign(train=part(train_idx, "train"), test=part(test_idx, "test"), truth=truth, model=model, q_true=q)


__all__ = ["FORMS", "OutsideEffect", "simulate_outside"]
