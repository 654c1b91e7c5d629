"""Calibrating a region gate's predictive standard deviation on residuals the model was not fitted on.

:class:`~torchcal.effects.region.RegionGate` predicts ``var = k^2 a + g^2 f^2 + b`` per sample and tracker axis
(:mod:`torchcal.effects.region`, *Predictive standard deviation*). Its parts come from different places: the
network's part ``a`` from the weight covariance of the filter that estimated it, the noise from the tracker and the
joints (:func:`observation_sigma`), the far part ``s_far`` from the fallback's residual scale on samples it was not
fitted on (:func:`residual_scale`), the fallback's own error and its growth with the distance from residuals of
geometric models on samples after the ones they were fitted on (:func:`fallback_growth`), and the scale ``k`` and
floor ``f`` from the residuals of a validation block and, where there are any, of held-out samples
(:func:`calibrate_predictive_sigma`, :func:`~torchcal.effects.region.fit_predictive_scale`).

This module holds the computations on residuals and gates; fitting the models whose residuals they are (the
geometry refits, the filters) is the caller's (the integrated method, :mod:`torchcal.pipeline.integrated`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from torchcal.effects import region as gating
from torchcal.effects.base import Context
from torchcal.effects.model import MeasurementModel

if TYPE_CHECKING:
    from torchcal.data import Measurements
    from torchcal.robot.model import RobotModel

Tensor = torch.Tensor

#: the share of residual components within two predicted standard deviations the scale factor is calibrated to
COVERAGE_TARGET = 0.95

#: a predictive sigma this many times the largest residual of the blocks it was calibrated on is numerical trouble:
#: half the cap of the widening factor (region.FACTOR_SIGMA_RATIO), so that a capped factor is always reported
SIGMA_CHECK_RATIO = 0.5 * gating.FACTOR_SIGMA_RATIO


def observation_sigma(robot: RobotModel, m: Measurements, sigma_tracker: float, sigma_joint: float) -> Tensor:
    """Measurement noise per tracker axis ``(3,)`` [m]: the tracker's and the joint noise at the probe, combined.

    Args:
        robot: the robot whose probe Jacobian carries the joint noise to the probe.
        m: the samples; the median of their per-point sigmas replaces ``sigma_tracker`` where they have them.
        sigma_tracker: the tracker's standard deviation per axis [m].
        sigma_joint: the joints' standard deviation [rad]; at the probe ``sigma_joint |J_q|_F / sqrt(3)`` per axis
            (median over the samples).
    """
    tracker = float(m.sigma.median()) if m.sigma is not None else sigma_tracker
    with torch.no_grad():
        _, Jq = robot.probe_jacobian(m.q)
    joint = sigma_joint * float(Jq.flatten(-2).norm(dim=-1).median()) / math.sqrt(3.0)
    return torch.full((3,), math.hypot(tracker, joint), dtype=m.q.dtype, device=m.q.device)


def residuals(model: MeasurementModel, m: Measurements, gate: gating.RegionGate | None = None) -> Tensor:
    """Prediction minus measurement per tracker axis ``(N, 3)`` [m] of ``model`` on the trajectory ``m``.

    With ``gate``, the model's last effect is replaced by it (``model`` itself is left as it is).
    """
    if gate is not None:
        model = MeasurementModel(model.robot, [*model.effects[:-1], gate])
    with torch.no_grad():
        return model(Context.from_measurements(m, trajectory=True)) - m.p


def residual_scale(e: Tensor) -> Tensor:
    """RMS per tracker axis ``(3,)`` [m] of residuals ``e`` ``(N, 3)`` [m]."""
    return e.square().mean(dim=0).sqrt()


def sigma_length(length: float) -> float:
    """The length the model's own error fades with towards ``s_far``: the gate's own where it is finite, otherwise
    the longest finite one of :data:`~torchcal.effects.region.GATE_LENGTHS` (a length must be finite), in units of
    the joints' training spread."""
    return length if math.isfinite(length) else max(g for g in gating.GATE_LENGTHS if math.isfinite(g))


def predictive_gate(
    model: MeasurementModel,
    weight_cov: Tensor,
    weight_index: Tensor,
    region: Tensor,
    length: float,
    fallback,
    noise: Tensor,
    far: Tensor,
    sigma_length: float,
    scale: float = 1.0,
    floor=None,
) -> gating.RegionGate:
    """``model``'s last (learned) effect behind a new region gate that also predicts its standard deviation.

    Args:
        model: the model; its last effect is a network's correction, or a gate around one (then its inner effect).
        weight_cov: covariance of the network's weights in the filter's state ``(k, k)`` [the network's units].
        weight_index: their indices in the network's flat weights ``(k,)``.
        region: the joints the gate is around, the correction's calibrated region ``(M, dof)`` [rad].
        length: the gate's length [spreads] (inf: no gate).
        fallback: the robot the prediction fades to, or None.
        noise, far: ``s_noise`` and ``s_far`` per tracker axis ``(3,)`` [m].
        sigma_length: the length ``s_far`` is approached with [spreads] (finite; :func:`sigma_length`).
        scale, floor: ``k`` and ``f`` per axis [m] (:meth:`~torchcal.effects.region.RegionGate.set_predictive`).
    """
    inner = model.effects[-1]
    inner = inner.inner if isinstance(inner, gating.RegionGate) else inner
    gate = gating.RegionGate(inner, region, length, fallback=fallback)
    gate.set_predictive(weight_cov, weight_index, noise, far, sigma_length, scale, floor)
    return gate


@dataclass(frozen=True)
class GatedBlock:
    """Residuals of a model behind its predictive gate on a block of samples it was not fitted on.

    Attributes:
        gate: the model's gate (:func:`predictive_gate`).
        robot: the model's robot (the gate's variance is rotated into the tracker frame with it).
        q: the block's joints ``(N, dof)`` [rad].
        e: the model's residuals there ``(N, 3)`` [m] (:func:`residuals` with ``gate``).
    """

    gate: gating.RegionGate
    robot: RobotModel
    q: Tensor
    e: Tensor

    @property
    def n(self) -> int:
        return len(self.e)

    def variance_parts(self) -> tuple[Tensor, Tensor, Tensor]:
        """``(e, a, b, g2)``: the residuals and the gate's variance parts there, each ``(N, 3)``."""
        with torch.no_grad():
            return (self.e, *self.gate.variance_parts(self.robot, self.q))

    def predictive_std(self) -> Tensor:
        """The gate's predicted standard deviation at the block's samples ``(N, 3)`` [m]."""
        with torch.no_grad():
            return self.gate.predictive_std(self.robot, self.q)


def fallback_growth(
    e: Tensor, d: Tensor, e_fallback: Tensor | None = None, d_fallback: Tensor | None = None
) -> tuple[list[float], float]:
    """The fallback's residual scale ``s_fb`` per axis [m] and its growth ``c`` with the squared distance
    [1 / spread^2] (:func:`~torchcal.effects.region.fit_fallback_growth`).

    The growth's shape comes from geometric models' residuals ``e`` ``(N, 3)`` [m] on samples after the ones each was
    fitted on, at their distances ``d`` ``(N,)`` [spreads] from those: a path's continuation can leave the region
    much further than a validation block next to it does, and samples further along show how far geometry's
    residual grows. Where the fallback itself has residuals ``e_fallback`` ``(M, 3)`` [m] on samples it was not
    fitted on, at distances ``d_fallback`` ``(M,)``, they size ``s_fb`` with that growth
    (:func:`~torchcal.effects.region.fit_fallback_scale`): a geometry fitted on all training samples is better
    determined than the ones fitted on parts of them, and scaled by those it would overstate its own error.
    """
    s_fb, growth = gating.fit_fallback_growth(e, d)
    if e_fallback is None:
        return s_fb, growth
    return gating.fit_fallback_scale(e_fallback, d_fallback, growth), growth


def calibrate_predictive_sigma(
    validation: GatedBlock,
    final: gating.RegionGate,
    holdout: GatedBlock | None,
    growth_residuals: Tensor,
    growth_distance: Tensor,
    fallback_residuals: Tensor | None = None,
    target: float = COVERAGE_TARGET,
) -> dict:
    """Calibrate the predictive standard deviation of two gates of the same choice of model; returns the evidence.

    ``validation`` is the candidate fitted on the fitting samples, behind its gate, on the validation block;
    ``final`` the gate of the same choice fitted on all training samples, and ``holdout`` its block on the
    held-out samples (``holdout.gate`` is ``final``; None without held-out samples). Both gates get, in place:

    * the fallback's scale and growth (:func:`fallback_growth`) from ``growth_residuals`` ``(N, 3)`` [m] at
      ``growth_distance`` ``(N,)`` [spreads] and, sizing the scale, ``fallback_residuals`` ``(M, 3)`` [m]: the final
      gate's fallback's residuals on the held-out samples (at their distance from ``final``'s region);
    * the scale ``k`` and floor ``f`` (:func:`~torchcal.effects.region.fit_predictive_scale`): by likelihood on
      validation, then widened (never narrowed) to ``target`` within 2 sigma over the validation and held-out
      residuals together, each block with its own gate's variance. The held-out coverage is then part of the
      calibration, not an independent check.

    Returns:
        the report's evidence: scale, floor, the coverage of 2 sigma on each block, the rule, the variance's parts
        (noise, far parts, fallback) and :func:`sigma_check` of both blocks.
    """
    if holdout is not None and holdout.gate is not final:
        raise ValueError("the held-out block must be the final gate's")
    d_fallback = None if holdout is None else final.distance(holdout.q)
    fb_sigma, fb_growth = fallback_growth(growth_residuals, growth_distance, fallback_residuals, d_fallback)
    for g in (validation.gate, final):
        g.sigma_fallback, g.fallback_growth = fb_sigma, fb_growth
    scale, floor = gating.fit_predictive_scale(
        *validation.variance_parts(), target, holdout=None if holdout is None else holdout.variance_parts()
    )
    for g in (validation.gate, final):
        g.sigma_scale, g.sigma_floor = scale, floor
    blocks = [(b.e, b.predictive_std()) for b in (validation, holdout) if b is not None]
    return {
        "scale": scale,
        "floor_mm": [f * 1e3 for f in floor],
        "target_coverage_2sigma": target,
        "calibration": "likelihood on validation, then widened (never narrowed) to the target over validation and "
        "held-out residuals together (held-out coverage calibrated, not independent)"
        if holdout is not None
        else "likelihood on validation, then widened (never narrowed) to the target on validation",
        "coverage_2sigma_validation": gating.coverage(*blocks[0]),
        "coverage_2sigma_holdout": gating.coverage(*blocks[1]) if holdout is not None else None,
        "n_validation": validation.n,
        "n_holdout": 0 if holdout is None else holdout.n,
        "sigma_noise_mm": (validation.gate.sigma_noise * 1e3).tolist(),
        "sigma_far_mm": (validation.gate.sigma_far * 1e3).tolist(),
        "sigma_far_final_mm": (final.sigma_far * 1e3).tolist(),
        "sigma_length": final.sigma_length,
        "fallback_sigma_mm": [x * 1e3 for x in fb_sigma],
        "fallback_growth": fb_growth,
        "sigma_check": sigma_check(blocks),
    }


def sigma_check(blocks: list[tuple[Tensor, Tensor]]) -> dict:
    """The largest predicted standard deviation of ``(residuals, sigma)`` blocks (``(N, 3)`` [m] each) against their
    largest residual.

    ``suspect`` when it is not finite or more than :data:`SIGMA_CHECK_RATIO` times that residual. The widening
    factor (:func:`~torchcal.effects.region.calibrate_factor`) is a quantile of what each residual component needs
    from the near part of the variance; where that part is nearly zero (a gate almost closed) the need, and with it
    every other sample's sigma, grows until the factor's cap. Reported, not hidden.

    Returns:
        ``max_sigma_mm`` (None if not finite), ``max_residual_mm``, ``ratio`` (None if not finite), ``suspect``.
    """
    sd = torch.cat([b[1].flatten() for b in blocks])
    e = torch.cat([b[0].abs().flatten() for b in blocks])
    top, worst = float(sd.max()), float(e.max().clamp_min(1e-12))
    ratio = top / worst
    return {
        "max_sigma_mm": top * 1e3 if math.isfinite(top) else None,
        "max_residual_mm": worst * 1e3,
        "ratio": ratio if math.isfinite(ratio) else None,
        "suspect": not math.isfinite(ratio) or ratio > SIGMA_CHECK_RATIO,
    }
