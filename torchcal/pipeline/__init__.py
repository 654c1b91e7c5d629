"""The calibration pipeline: the top of the library, the only layer that imports the closed loop and the filters.

:func:`calibrate` (:mod:`torchcal.pipeline.run`) runs a method, a declared sequence of stages
(:mod:`torchcal.pipeline.methods`), over a typed, frozen run state (:mod:`torchcal.pipeline.state`): each stage
reads the run and returns a :class:`StageResult` with its typed records (:mod:`torchcal.pipeline.records`), and
only :func:`calibrate` applies it. The stages: the closed loop (:mod:`~torchcal.pipeline.loop`), the learned stage
(:mod:`~torchcal.pipeline.learned`), the integrated ANN-EKF (:mod:`~torchcal.pipeline.integrated`) and the held-out
guards and refit (:mod:`~torchcal.pipeline.holdout`).
"""

from torchcal.pipeline.options import DEFAULT_METHOD, METHODS, Options
from torchcal.pipeline.prior import MIN_PRIOR_POSES, Prior, PriorUpdate, prior_from_run
from torchcal.pipeline.records import Cause, EffectRecord, Note, Rejection, StageName
from torchcal.pipeline.run import calibrate, check_holdout, holdout_split, is_trajectory, min_poses
from torchcal.pipeline.state import CalibrationRun, Checkpoint, StageResult

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "MIN_PRIOR_POSES",
    "CalibrationRun",
    "Cause",
    "Checkpoint",
    "EffectRecord",
    "Note",
    "Options",
    "Prior",
    "PriorUpdate",
    "Rejection",
    "StageName",
    "StageResult",
    "calibrate",
    "check_holdout",
    "holdout_split",
    "is_trajectory",
    "min_poses",
    "prior_from_run",
]
