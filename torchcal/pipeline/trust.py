"""A finished run's predictive standard deviation (:mod:`torchcal.estimate.trust`) measured on its held-out rows: of
the model it writes, and of its kinematic calibration where the two differ (beyond the calibrated region the one
with the far smaller sigma predicts)."""

from __future__ import annotations

import copy
import dataclasses
import functools
from dataclasses import dataclass

import torch

from torchcal import _console
from torchcal.effects import Context, MeasurementModel
from torchcal.errors import EstimationError
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.estimate.fit import fit_covariance
from torchcal.estimate.trust import FewRows, Trust, few_rows, fit_trust
from torchcal.pipeline.beyond import Choice, bounded, choose, nominal_covariance, nominal_model, physical_model
from torchcal.pipeline.records import StageName
from torchcal.pipeline.state import CalibrationRun


@dataclass(frozen=True)
class RunTrust:
    """The final model's :class:`Trust`, and the kinematic calibration's with its model and covariance where the
    final model is not it (None otherwise: a kinematic run, or one whose guard stepped back to it); the nominal
    model's (the first stage's, with its covariance: :func:`~torchcal.pipeline.beyond.nominal_covariance`), the
    physical model's (the final one without its fading parts, where it has some) and which of them predicts beyond
    the region (:func:`~torchcal.pipeline.beyond.choose`); where that is the full or the physical model, its
    covariance bounded by the tolerance priors (:func:`~torchcal.pipeline.beyond.bounded`) and its trust measured
    with it: the sigma of the rows beyond."""

    full: Trust | None
    geometric_model: MeasurementModel | None = None
    geometric_covariance: ParameterCovariance | None = None
    geometric: Trust | None = None
    few: FewRows | None = None  # the final model's, where too few rows were held out to measure ``full``
    nominal_model: MeasurementModel | None = None
    nominal_covariance: ParameterCovariance | None = None
    nominal: Trust | None = None
    physical: Trust | None = None
    choice: Choice | None = None
    beyond_covariance: ParameterCovariance | None = None
    beyond: Trust | None = None


def noise_of(run: CalibrationRun) -> tuple[float, float, float]:
    """The instrument's standard deviation per axis [m]: the training rows' median where they carry their own, else
    the run's tracker noise."""
    s = run.train.sigma
    if s is not None and len(s):
        med = s.median(dim=0).values
        return float(med[0]), float(med[1]), float(med[2])
    v = float(run.options.fit.sigma_tracker)
    return v, v, v


def _held_out(
    run: CalibrationRun, model: MeasurementModel, cov: ParameterCovariance | None, measure=fit_trust
) -> Trust | FewRows | None:
    """``model``'s :class:`Trust` (or what ``measure`` gives: :func:`few_rows`) on the run's held-out rows, measured
    on the CPU (as predict computes it)."""
    hold = run.hold.to("cpu")
    if hold.p is None or hold.n == 0:
        return None
    ctx = Context.from_measurements(hold, trajectory=run.trajectory)
    return measure(model, cov, ctx, hold.p, noise_of(run))


def _geometric_covariance(run: CalibrationRun, model: MeasurementModel) -> ParameterCovariance | None:
    fit = next((f for f in run.fits if f.stage == StageName.GEOMETRIC), None)
    if fit is None:
        return None
    # with the elements it held near nominal by the prior (a consider covariance): their doubt is the kinematic
    # calibration's own, where a pose moves them
    return _of_model(fit_covariance(fit), model)


def _of_model(cov: ParameterCovariance | None, model: MeasurementModel) -> ParameterCovariance | None:
    """``cov`` where every parameter it is about is one of ``model``'s (a run stepped back to an earlier stage keeps
    the covariance of a fit whose effects it dropped: that one says nothing of this model), else None."""
    params = dict(model.named_parameters())
    return cov if cov is not None and all(n in params for n in cov.names) else None


def run_trust(run: CalibrationRun) -> RunTrust:
    """Measure the run's :class:`RunTrust` on its held-out rows (those no fit of the final model saw)."""
    with torch.no_grad():
        model = copy.deepcopy(run.model).to("cpu")
        full = _held_out(run, model, _of_model(run.covariance, model))
        few = None if full is not None else _held_out(run, model, _of_model(run.covariance, model), few_rows)
        out = RunTrust(full, few=few)
        candidates = {"full": model}
        geo = next((s.model for s in run.stages if s.name == StageName.GEOMETRIC), None)
        if geo is not None and (run.model.effects or geo.effects):
            geo = copy.deepcopy(geo).to("cpu")
            geo.set_region(run.model.region, fade=False)
            cov = _geometric_covariance(run, geo)
            out = RunTrust(full, geo, cov, _held_out(run, geo, cov), few=few)
            candidates["geometric"] = geo
        physical = physical_model(model)
        if physical is not None:
            candidates["physical"] = physical
            out = dataclasses.replace(out, physical=_held_out(run, physical, _of_model(run.covariance, physical)))
    nominal = nominal_model(run)
    if nominal is None or run.prior is not None:  # an update's first stage is the prior run's model, not nominal
        return out
    ncov = nominal_covariance(run, nominal)
    with torch.no_grad():
        out = dataclasses.replace(
            out, nominal_model=nominal, nominal_covariance=ncov, nominal=_held_out(run, nominal, ncov)
        )
        candidates["nominal"] = nominal
        try:
            choice = choose(run, candidates)
        except (RuntimeError, EstimationError) as e:  # a refit that cannot be solved: no choice, and it is said
            _console.info(f"warning: no model chosen for the rows beyond the region ({type(e).__name__}: {e})")
            choice = Choice(None, 0, {}, 0.0, f"none: the comparison failed ({type(e).__name__})")
        out = dataclasses.replace(out, choice=choice)
        if out.choice.model not in ("full", "physical"):
            return out
        m = candidates[out.choice.model]
        cov = bounded(_of_model(run.covariance, m), m, run)
        measured = out.full if m is model else out.physical
        if isinstance(measured, Trust):  # the same model at the same rows: its variogram as measured, not again
            measure = functools.partial(fit_trust, variogram=(measured.lags, measured.rho))
            return dataclasses.replace(out, beyond_covariance=cov, beyond=_held_out(run, m, cov, measure))
        return dataclasses.replace(out, beyond_covariance=cov, beyond=_held_out(run, m, cov))
