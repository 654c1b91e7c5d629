"""Typed records of a calibration run: stage names, the effects it kept and the candidates it rejected.

Each step of the pipeline returns its records and the run appends them (:class:`~torchcal.pipeline.run.
CalibrationRun`); ``report.json`` writes them with ``to_dict`` (CONTRACT §4: the ``effects`` and ``rejected``
lists). The enums are str-valued, so JSON and string comparisons see the plain names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum


class StageName(str, Enum):
    """The fixed stages of a run; a named effect's stage is called by the effect's label instead."""

    NOMINAL = "nominal"  #: nominal geometry, tracker pose and lever arm fitted
    GEOMETRIC = "geometric"  #: after the kinematic calibration
    LEARNED = "learned"  #: with a learned residual model
    INTEGRATED = "integrated"  #: after the integrated ANN-EKF

    def __str__(self) -> str:  # f-strings and str() give the value on every Python version
        return self.value


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


@dataclass
class Rejection(_Entry):
    """A candidate that did not earn its place, with the reason and the evidence."""

    evidence: dict = field(default_factory=dict)
    name: str | None = None
    reason: str | None = None

    def to_dict(self) -> dict:
        return {**self._head(name=self.name, reason=self.reason), "evidence": self.evidence}
