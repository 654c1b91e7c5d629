"""Typed records of a calibration run: stage names, the effects it kept, the candidates it rejected, its notes,
the closed loop's search and the integrated filter's pass.

Each stage returns its records in a :class:`~torchcal.pipeline.state.StageResult` and the run appends them
(:meth:`~torchcal.pipeline.state.CalibrationRun.apply`); ``report.json`` writes them with ``to_dict`` (the
``effects`` and ``rejected`` lists). The enums are str-valued, so JSON and string comparisons see the plain names.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import Enum

import torch

from torchcal.diagnose.candidates import Candidate
from torchcal.diagnose.score import Score
from torchcal.filter.ekf import EKFConfig, EKFResult

Tensor = torch.Tensor


class StageName(str, Enum):
    """The fixed stages of a run; a named effect's stage is called by the effect's label instead."""

    NOMINAL = "nominal"  #: nominal geometry, tracker pose and lever arm fitted
    GEOMETRIC = "geometric"  #: after the kinematic calibration
    LEARNED = "learned"  #: with a learned residual model
    INTEGRATED = "integrated"  #: after the integrated ANN-EKF

    def __str__(self) -> str:  # f-strings and str() give the value on every Python version
        return self.value


class Note(str):
    """A line of the run's story, with the stage that said it (``stage``). A ``str``, so the report and a reader
    see plain text."""

    stage: str

    def __new__(cls, stage: str, text: str) -> Note:
        note = super().__new__(cls, text)
        note.stage = stage
        return note

    def __reduce__(self):  # pickled and copied as a note, not as a bare str
        return (Note, (self.stage, str(self)))


def _given(**fields) -> dict:
    """The fields that are not None, in the order given (report.json leaves the others out)."""
    return {k: v for k, v in fields.items() if v is not None}


@dataclass
class _Entry:
    """What an effect record and a rejection share: the effect kind and its joint, written first."""

    kind: str  # the effect kind (:data:`torchcal.effects.KINDS`)
    joint: int | None  # 1-based joint, or None

    def _head(self, **optional) -> dict:
        """``kind`` and ``joint``, then the ``optional`` fields that are not None."""
        return {"kind": self.kind, "joint": self.joint, **_given(**optional)}


@dataclass
class EffectRecord(_Entry):
    """An effect the run kept, with its parameters and the evidence for it.

    Attributes:
        kind: the effect kind (:data:`torchcal.effects.KINDS`).
        joint: 1-based joint, or None.
        name: the candidate's name (``compliance:2``), None where the step has none.
        label: the effect's label, which is also the name of its stage.
        params: parameter estimates and settings.
        evidence: the tests that admitted it.
        rmse_before_mm, rmse_after_mm: held-out RMSE of the stages before and after it [mm].
    """

    params: dict
    evidence: dict
    name: str | None = None
    label: str | None = None
    rmse_before_mm: float | None = None
    rmse_after_mm: float | None = None

    def to_dict(self) -> dict:
        return {
            **self._head(name=self.name, label=self.label),
            "params": self.params,
            "evidence": self.evidence,
            **_given(rmse_before_mm=self.rmse_before_mm, rmse_after_mm=self.rmse_after_mm),
        }


class Cause(str, Enum):
    """Why a candidate was rejected, as a type (the rejection's ``reason`` says it in words, with the numbers)."""

    VALIDATION = "validation"  #: the validation poses do not confirm the gain
    EDGE = "edge"  #: it wins in the middle of its joint's range and loses at the edges
    ILL_DETERMINED = "ill_determined"  #: it fits the poses but is not determined, or too large, beyond them
    REFIT_FAILED = "refit_failed"  #: its joint refit failed (rank deficient with it)
    SELECTION = "selection"  #: a learned model or filter that does not beat the model without it
    EXPLAINED = "explained"  #: dropped after the learned stage: the learned model explains it as well
    HOLDOUT_GUARD = "holdout_guard"  #: dropped by the held-out guard: the run is better without it

    def __str__(self) -> str:
        return self.value


@dataclass
class Rejection(_Entry):
    """A candidate that did not earn its place, with the typed cause, the reason in words and the evidence."""

    evidence: dict = field(default_factory=dict)
    name: str | None = None
    reason: str | None = None
    cause: Cause | None = None

    def to_dict(self) -> dict:
        head = self._head(name=self.name, reason=self.reason, cause=None if self.cause is None else str(self.cause))
        return {**head, "evidence": self.evidence}


@dataclass
class Decision:
    """One candidate that reached validation: accepted or not, with the evidence."""

    round: int
    candidate: Candidate
    score: Score
    accepted: bool
    why: str  # the loop's verdict
    validation: dict
    stage: str | None = None  # the stage an accepted effect opened
    models: tuple | None = None  # (before, after) models for the plots; after fitted on the training poses
    dropped: str | None = None  # why a later stage dropped the accepted effect again

    @property
    def reason(self) -> str:
        """The verdict, and the later drop if any."""
        return self.why if self.dropped is None else f"{self.why}; {self.dropped}"

    def to_dict(self) -> dict:
        return {
            "round": self.round,
            **self.candidate.to_dict(),
            "accepted": self.accepted,
            "reason": self.reason,
            "score": self.score.to_dict(),
            "validation": self.validation,
            "stage": self.stage,
        }


@dataclass
class Diagnosis:
    """Everything the loop looked at, for the report."""

    alpha: float
    alpha_validation: float
    n_fit: int
    n_validation: int
    candidates: list[Candidate]
    skipped: list[dict]
    rounds: list[dict] = field(default_factory=list)  # per round: scores and the global test before it
    decisions: list[Decision] = field(default_factory=list)
    stop: str = ""
    unexplained: list[dict] = field(default_factory=list)  # tracing.unexplained_entries of the final model
    trades: list[dict] = field(default_factory=list)  # loop.effect_trades of the final fit: effects vs geometry
    stations: list[dict] = field(default_factory=list)  # diagnose.stations: each instrument effect at each station

    def to_dict(self) -> dict:
        return {
            "method": "score tests at the current fit (Bonferroni over the candidates), joint refit, "
            "confirmation on validation poses (paired one-sided test)",
            "alpha": self.alpha,
            "alpha_validation": self.alpha_validation,
            "n_fit": self.n_fit,
            "n_validation": self.n_validation,
            "candidates": [c.name for c in self.candidates],
            "skipped": self.skipped,
            "rounds": [
                {
                    "round": r["round"],
                    "global_test": r["global_test"],
                    "scores": [s.to_dict() for s in r["scores"]],
                    **{k: r[k] for k in ("localisation", "open_candidates", "open_notes") if k in r},
                }
                for r in self.rounds
            ],
            "decisions": [d.to_dict() for d in self.decisions],
            "stop": self.stop,
            **({"trades": [{k: v for k, v in t.items() if k != "note"} for t in self.trades]} if self.trades else {}),
            **({"instrument_stations": self.stations} if self.stations else {}),
        }

    def copy(self) -> Diagnosis:
        """A copy a later stage may amend (its decisions and lists its own; candidates, scores and models shared)."""
        return dataclasses.replace(
            self,
            decisions=[dataclasses.replace(d) for d in self.decisions],
            rounds=list(self.rounds),
            unexplained=list(self.unexplained),
        )

    def drop(self, stage: str, why: str) -> None:
        """Mark the decisions that opened ``stage`` as dropped by a later stage, with ``why``."""
        for d in self.decisions:
            if d.stage == stage:
                d.dropped = why


def _first_draw(name: str) -> property:
    """The filter result's ``name`` ``(N, 3)`` [m] of its only draw: an integrated run makes one pass."""
    return property(lambda self: getattr(self.result, name)[0], doc=f"The filter's {name} per sample (N, 3) [m].")


@dataclass
class IntegratedFilter:
    """The filter pass of an ``integrated`` run, with the references the report compares it with.

    All per-sample tensors cover the training samples, then the held-out ones ``(N, 3)`` [m], tracker frame.
    """

    result: EKFResult  # the pass (draw dimension 1)
    y: Tensor  # measured positions
    kinematic: Tensor  # prediction of the calibrated kinematic model alone
    n_train: int
    config: EKFConfig
    w_start: Tensor  # the weights the filter started from (after steps 2-3)
    weight_cov: Tensor | None = None  # final covariance of the weights in the filter's state (k, k)
    weight_index: Tensor | None = None  # their indices in the network's flat weights (k,)

    geometric = _first_draw("geometric")
    nongeometric = _first_draw("nongeometric")
    prediction = _first_draw("prediction")

    def deviations(self) -> dict[str, Tensor]:
        """``devG``, ``devNG``, ``devAll`` per sample ``(N, 3)`` [m] (the paper's Figs. 9 and 11 on measured data).

        Without a truth, the measurement is split at the calibrated kinematic model: geometric reference
        ``G = T p(theta)``, non-geometric reference ``NG = y - G``. Then ``devG = G_filter - G``,
        ``devNG = NG_filter - NG`` and ``devAll = devG + devNG = prediction - y`` (tracker noise included).
        """
        G, NG = self.kinematic, self.y - self.kinematic
        return {"devG": self.geometric - G, "devNG": self.nongeometric - NG, "devAll": self.prediction - self.y}
