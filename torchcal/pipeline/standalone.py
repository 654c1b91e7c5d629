"""The geometry a run's exports carry where its effects cannot go with them: the chain that predicts best alone.

A default-method run fits its geometry together with its effects (compliance, a transmission error, a learned
field): that geometry leans on the effects and, loaded without them by a controller or a ROS description, predicts
worse than a plain kinematic calibration would have. So a run with effects keeps, beside its model, a stand-alone
geometry chosen on the held-out rows (which no candidate saw) from two candidates:

* ``kinematic``: the run's kinematic calibration (the geometric stage, fitted to the training rows alone);
* ``refit``: the geometry, instrument pose and lever arm fitted to the full model's predictions at the training
  rows' joints (the region the run knows), so the chain absorbs as much of the effects as a rigid chain can.

The ``cofitted`` geometry (the run's own, effects dropped) is measured beside them for ``export --geometry
cofitted``. :mod:`torchcal.report.rundir` writes the choice as ``standalone.pt``, its numbers in model.json's
``standalone`` and the held-out rows' joints and positions in ``holdout.pt`` (``check-export`` measures a file on
them).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from torchcal import _console
from torchcal.effects import Context, MeasurementModel
from torchcal.errors import TorchcalError
from torchcal.estimate.fit import FAILED, GEOMETRIC_GROUPS, errors, solve
from torchcal.pipeline.records import StageName
from torchcal.pipeline.state import CalibrationRun
from torchcal.stats import rmse

Tensor = torch.Tensor
#: the candidates, in the order a tie goes
SOURCES = ("kinematic", "refit")


@dataclass(frozen=True)
class Standalone:
    """The stand-alone geometry of a run with effects.

    Attributes:
        model: geometry, instrument pose and lever arm; no effects (CPU, float64).
        source: which candidate it is (:data:`SOURCES`).
        rmse_mm: its held-out RMSE alone [mm].
        rmse_full_mm: the run's model's held-out RMSE, effects included [mm].
        rmse_cofitted_mm: the run's own geometry's held-out RMSE with its effects dropped [mm].
        candidates: each candidate's held-out RMSE [mm].
    """

    model: MeasurementModel
    source: str
    rmse_mm: float
    rmse_full_mm: float
    rmse_cofitted_mm: float
    candidates: dict[str, float]

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "rmse_holdout_mm": self.rmse_mm,
            "rmse_full_mm": self.rmse_full_mm,
            "rmse_cofitted_mm": self.rmse_cofitted_mm,
            "candidates_mm": dict(self.candidates),
        }


def without_effects(model: MeasurementModel) -> MeasurementModel:
    """A copy of ``model``'s robot (geometry, instrument pose, lever arm) as a model of its own, on the CPU."""
    out = MeasurementModel(copy.deepcopy(model.robot).to("cpu"))
    if model.region is not None:
        out.set_region(model.region.to("cpu"), fade=False)
    return out


def refit_to_model(run: CalibrationRun) -> MeasurementModel | None:
    """The rigid chain closest to the run's model over its training rows: geometry, instrument pose and lever arm
    fitted to the model's predicted positions there (noise-free targets, the geometric fit's identifiability), from
    the kinematic calibration's values. None where the fit fails."""
    geo = next((s.model for s in run.stages if s.name == StageName.GEOMETRIC), None)
    fit0 = next((f for f in run.fits if f.stage == StageName.GEOMETRIC), None)
    if geo is None:
        return None
    train = run.train.to("cpu").without_orientation()
    full = copy.deepcopy(run.model).to("cpu")
    with torch.no_grad():
        target = full(Context.from_measurements(train, trajectory=run.trajectory))
    out = without_effects(geo)
    ida = fit0.identifiability if fit0 is not None else None
    try:
        fit = solve(
            out,
            train.with_positions(target),
            GEOMETRIC_GROUPS,
            run.options.fit,
            "stand-alone geometry",
            trajectory=run.trajectory,
            identifiability=ida,
        )
    except TorchcalError as e:  # numerical trouble: the kinematic candidate stands alone
        _console.info(
            f"torchcal: note: the stand-alone refit of the geometry failed ({e}); exports keep the kinematic one"
        )
        return None
    return None if fit.result.status in FAILED else out


def standalone(run: CalibrationRun) -> Standalone | None:
    """The run's :class:`Standalone` geometry, chosen on its held-out rows; None where the run's model has no effects
    (its geometry stands alone as it is) or no held-out rows with positions to choose on."""
    hold = run.hold.to("cpu")
    if not run.model.effects or hold.p is None or hold.n == 0:
        return None
    geo = next((s.model for s in run.stages if s.name == StageName.GEOMETRIC), None)
    candidates: dict[str, MeasurementModel] = {}
    if geo is not None:
        candidates["kinematic"] = without_effects(geo)
    refit = refit_to_model(run)
    if refit is not None:
        candidates["refit"] = refit
    if not candidates:
        return None
    scores = {k: rmse(errors(m, hold, run.trajectory)) * 1e3 for k, m in candidates.items()}
    best = min(SOURCES, key=lambda k: scores.get(k, float("inf")))
    full = copy.deepcopy(run.model).to("cpu")
    return Standalone(
        model=candidates[best],
        source=best,
        rmse_mm=scores[best],
        rmse_full_mm=rmse(errors(full, hold, run.trajectory)) * 1e3,
        rmse_cofitted_mm=rmse(errors(without_effects(full), hold, run.trajectory)) * 1e3,
        candidates=scores,
    )


__all__ = ["SOURCES", "Standalone", "refit_to_model", "standalone", "without_effects"]
