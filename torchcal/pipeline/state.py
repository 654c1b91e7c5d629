"""The typed state of a calibration run, and the frozen result a stage returns.

A stage is a function ``CalibrationRun -> StageResult`` (:data:`StageFn`); what it leaves in the story is a
:class:`Checkpoint`. It works on its own :class:`StageWork` (a copy of the run's model and of the story so far)
and never edits the run; only :func:`torchcal.pipeline.run.calibrate` applies a result
(:meth:`CalibrationRun.apply`), which returns a new run.
The result says what the stage changed: the model it ends with, the checkpoints of the before/after story it
added or dropped, its least-squares fits, the effects it added, amended or dropped, its rejections and notes.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from torchcal import stats as S
from torchcal.data import Measurements
from torchcal.effects import MeasurementModel
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.estimate.fit import Fit, errors
from torchcal.estimate.robust import Screening
from torchcal.pipeline.options import Options
from torchcal.pipeline.prior import Prior, PriorUpdate
from torchcal.pipeline.records import Diagnosis, EffectRecord, IntegratedFilter, Note, Rejection
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor


@dataclass(frozen=True)
class Checkpoint:
    """A checkpoint of the before/after story: the model as it stood, with its held-out and training errors."""

    name: str  # a StageName, or the label of the named effect the stage added
    model: MeasurementModel
    holdout_errors: Tensor  # (N_holdout,) m
    train_errors: Tensor

    @property
    def rmse(self) -> float:
        return S.rmse(self.holdout_errors)


def last_identifiability(fits):
    """The identifiability analysis of the last of ``fits`` that made one (None where none did)."""
    return next((f.identifiability for f in reversed(fits) if f.identifiability is not None), None)


@dataclass(frozen=True)
class CalibrationRun:
    """Everything a calibration did: the data and their split, the model, the story, the fits and the records.

    Frozen: a stage reads it and returns a :class:`StageResult`; :meth:`apply` makes the next state.
    """

    robot_spec: str
    model: MeasurementModel
    options: Options
    data: Measurements
    train_idx: Tensor
    holdout_idx: Tensor
    trajectory: bool
    split: S.Split | None = None  # the held-out split, with its revisit groups
    screening: Screening | None = None  # the gross errors left out
    stages: tuple[Checkpoint, ...] = ()
    fits: tuple[Fit, ...] = ()
    effects: tuple[EffectRecord, ...] = ()
    rejections: tuple[Rejection, ...] = ()  # candidates that did not earn their place
    notes: tuple[Note, ...] = ()
    covariance: ParameterCovariance | None = None  # of the last fit's free parameters (predict's sx, sy, sz)
    learned_validation_errors: Tensor | None = None  # per pose, of the learned stage's validation poses [m]
    diagnosis: Diagnosis | None = None  # the closed loop's search
    filter: IntegratedFilter | None = None  # the integrated method's filter pass
    holdout_guard: dict | None = None  # the held-out guard's evidence (torchcal.pipeline.holdout)
    prior: Prior | None = None  # the prior run the calibration started from (torchcal.pipeline.prior)
    prior_update: PriorUpdate | None = None  # what the new poses changed of it

    @property
    def robot(self) -> RobotModel:
        return self.model.robot

    @property
    def train(self) -> Measurements:
        return self.data.subset(self.train_idx)

    @property
    def hold(self) -> Measurements:
        return self.data.subset(self.holdout_idx)

    @property
    def fitted_and_held_out(self) -> Measurements:
        """The training samples, then the held-out ones (time order on a trajectory): what a refit uses."""
        return self.data.subset(torch.cat([self.train_idx, self.holdout_idx]))

    def stage(self, name: str) -> Checkpoint:
        """The first stage called ``name``."""
        return next(s for s in self.stages if s.name == name)

    @property
    def identifiability(self):
        """The identifiability analysis of the last fit that made one (None before the geometric fit)."""
        return last_identifiability(self.fits)

    @property
    def effects_report(self) -> list[dict]:
        """The kept effects as ``report.json`` writes them, their parameters as the final model holds them (an effect
        is recorded when it is admitted; later fits, with more effects beside it, move its values)."""
        return [_final_values(r.to_dict(), self.model, self.fits) for r in self.effects]

    @property
    def rejected(self) -> list[dict]:
        """The rejected candidates as ``report.json`` writes them."""
        return [r.to_dict() for r in self.rejections]

    def with_split(self, train_idx: Tensor, holdout_idx: Tensor) -> CalibrationRun:
        """The same run on another split of its data (a trial inside a stage), with no story and no records but its
        fits (the identifiability of its geometric fit)."""
        return dataclasses.replace(
            self, train_idx=train_idx, holdout_idx=holdout_idx, stages=(), effects=(), rejections=(), notes=()
        )

    def apply(self, result: StageResult) -> CalibrationRun:
        """The run after ``result``: its model, the story without the checkpoints it dropped and with those it
        added, the fits it kept and added, the effects without those it dropped, amended in place and appended."""
        stages = tuple(s for s in self.stages if s.name not in result.dropped_stages) + result.checkpoints
        fits = self.fits[: result.fits_kept if result.fits_kept is not None else len(self.fits)] + result.fits
        amended = {r.label: r for r in result.amended}
        effects = tuple(amended.get(r.label, r) for r in self.effects if r.label not in result.dropped_effects)
        changes = dict(
            stages=stages,
            fits=fits,
            effects=effects + result.effects,
            rejections=self.rejections + result.rejections,
            notes=self.notes + result.notes,
        )
        if result.model is not None:
            changes["model"] = result.model
        for f in dataclasses.fields(result):
            if f.metadata.get("replaces") and getattr(result, f.name) is not None:
                changes[f.name] = getattr(result, f.name)
        return dataclasses.replace(self, **changes)


#: the mark of a :class:`StageResult` field that replaces the run's field of the same name
_REPLACES = {"replaces": True}


@dataclass(frozen=True)
class StageResult:
    """What one stage changed (:meth:`CalibrationRun.apply` applies it)."""

    stage: str  # the stage that made it
    model: MeasurementModel | None = None  # the model the run goes on with (None: unchanged)
    checkpoints: tuple[Checkpoint, ...] = ()  # appended to the story
    dropped_stages: tuple[str, ...] = ()  # checkpoints taken out of the story, by name
    fits_kept: int | None = None  # how many of the run's fits stay (None: all)
    fits: tuple[Fit, ...] = ()  # appended after those
    effects: tuple[EffectRecord, ...] = ()  # appended
    amended: tuple[EffectRecord, ...] = ()  # replace the run's records of the same label
    dropped_effects: tuple[str, ...] = ()  # records taken out, by label
    rejections: tuple[Rejection, ...] = ()
    notes: tuple[Note, ...] = ()
    # the run's fields of the same name, replaced where set (None: unchanged); :meth:`CalibrationRun.apply` finds
    # them by this mark, so a field declared here with it is applied without a second list to keep in step
    covariance: ParameterCovariance | None = field(default=None, metadata=_REPLACES)
    learned_validation_errors: Tensor | None = field(default=None, metadata=_REPLACES)
    diagnosis: Diagnosis | None = field(default=None, metadata=_REPLACES)
    filter: IntegratedFilter | None = field(default=None, metadata=_REPLACES)
    holdout_guard: dict | None = field(default=None, metadata=_REPLACES)
    prior_update: PriorUpdate | None = field(default=None, metadata=_REPLACES)

    @property
    def changed(self) -> bool:
        """Whether applying it changes the run's model or story."""
        return self.model is not None or bool(self.checkpoints or self.dropped_stages or self.effects)


#: a stage: reads the run, returns what it changed
StageFn = Callable[[CalibrationRun], StageResult]


@dataclass
class StageWork:
    """A stage's own scratch, made from the run it reads: a copy of the model, the story and the records so far,
    and what the stage adds. The stage edits only this; :meth:`result` freezes the difference to the run.

    Read-only views of the run (``options``, ``data``, ``train``, ``hold`` ...) pass through.
    """

    run: CalibrationRun
    name: str
    model: MeasurementModel = None  # type: ignore[assignment]  # set in __post_init__ (a copy of the run's)
    stages: list[Checkpoint] = field(default_factory=list)
    fits: list[Fit] = field(default_factory=list)
    effects: list[EffectRecord] = field(default_factory=list)
    rejections: list[Rejection] = field(default_factory=list)
    notes: list[Note] = field(default_factory=list)
    diagnosis: Diagnosis | None = None
    filter: IntegratedFilter | None = None
    holdout_guard: dict | None = None
    learned_validation_errors: Tensor | None = None
    covariance: ParameterCovariance | None = None
    _amended: list[EffectRecord] = field(default_factory=list)

    def __post_init__(self):
        run = self.run
        if self.model is None:
            self.model = copy.deepcopy(run.model)
        self.stages = list(run.stages)
        self.fits = list(run.fits)
        self.effects = list(run.effects)
        self.diagnosis = run.diagnosis.copy() if run.diagnosis is not None else None
        self.learned_validation_errors = run.learned_validation_errors

    # the run's data, options and split, read-only
    options = property(lambda self: self.run.options)
    data = property(lambda self: self.run.data)
    train_idx = property(lambda self: self.run.train_idx)
    holdout_idx = property(lambda self: self.run.holdout_idx)
    trajectory = property(lambda self: self.run.trajectory)
    train = property(lambda self: self.run.train)
    hold = property(lambda self: self.run.hold)
    fitted_and_held_out = property(lambda self: self.run.fitted_and_held_out)

    @property
    def robot(self) -> RobotModel:
        return self.model.robot

    @property
    def identifiability(self):
        """The identifiability analysis of the last fit that made one, the stage's own fits included."""
        return last_identifiability(self.fits)

    def stage(self, name: str) -> Checkpoint:
        return next(s for s in self.stages if s.name == name)

    def add_stage(self, name: str) -> Checkpoint:
        """Append the model as it stands as checkpoint ``name``, with its held-out and training errors."""
        st = Checkpoint(
            name,
            copy.deepcopy(self.model),
            errors(self.model, self.hold, self.trajectory),
            errors(self.model, self.train, self.trajectory),
        )
        self.stages.append(st)
        return st

    def note(self, text: str) -> None:
        self.notes.append(Note(self.name, text))

    def amend(self, record: EffectRecord, **evidence) -> EffectRecord:
        """A record of the run with ``evidence`` added (the run's own record stays as it was)."""
        new = dataclasses.replace(record, evidence={**record.evidence, **evidence})
        self.effects[next(i for i, r in enumerate(self.effects) if r is record)] = new
        self._amended.append(new)
        return new

    def result(self, *, model_changed: bool = True) -> StageResult:
        """The frozen difference between this work and the run it was made from."""
        run = self.run
        old_stages, old_fits = {id(s) for s in run.stages}, list(run.fits)
        kept = 0
        while kept < min(len(old_fits), len(self.fits)) and self.fits[kept] is old_fits[kept]:
            kept += 1
        ours = {id(s) for s in self.stages}
        old_effects = {id(r) for r in run.effects}
        ours_effects = {id(r) for r in self.effects}
        amended = [r for r in self._amended if id(r) in ours_effects]
        touched = {id(r) for r in amended}
        replaced = {r.label for r in amended}
        return StageResult(
            stage=self.name,
            model=self.model if model_changed else None,
            checkpoints=tuple(s for s in self.stages if id(s) not in old_stages),
            dropped_stages=tuple(s.name for s in run.stages if id(s) not in ours),
            fits_kept=kept if kept < len(old_fits) else None,
            fits=tuple(self.fits[kept:]),
            effects=tuple(r for r in self.effects if id(r) not in old_effects and id(r) not in touched),
            amended=tuple(amended),
            dropped_effects=tuple(
                r.label for r in run.effects if id(r) not in ours_effects and r.label not in replaced
            ),
            rejections=tuple(self.rejections),
            notes=tuple(self.notes),
            covariance=self.covariance,
            learned_validation_errors=(
                self.learned_validation_errors
                if self.learned_validation_errors is not run.learned_validation_errors
                else None
            ),
            diagnosis=self.diagnosis if self.diagnosis is not None and self.diagnosis is not run.diagnosis else None,
            filter=self.filter,
            holdout_guard=self.holdout_guard,
        )


def _final_values(entry: dict, model, fits) -> dict:
    """``entry`` (an :class:`EffectRecord`'s dict) with each parameter's value and standard deviation from the final
    ``model`` and the last fit that estimated it; an effect the final model no longer holds is left as recorded."""
    from torchcal.estimate.fit import effect_parameters

    effects = getattr(model, "effects", None) or []
    index = next((i for i, e in enumerate(effects) if e.label() == entry.get("label")), None)
    params = entry.get("params")
    if index is None or not isinstance(params, dict):
        return entry
    prefix = f"{effects[index].label()}."
    fit = next((f for f in reversed(fits) if any(n.startswith(prefix) for n in getattr(f.result, "names", ()))), None)
    if fit is None:
        return entry
    final = effect_parameters(model, index, fit)
    # a held element keeps the note its record gave it (why it is held), not the final fit's generic one
    merged = {
        k: ({**v, **final[k], **{n: v[n] for n in ("note",) if n in v and n in final[k]}})
        if isinstance(v, dict) and k in final
        else v
        for k, v in params.items()
    }
    return {**entry, "params": merged}
