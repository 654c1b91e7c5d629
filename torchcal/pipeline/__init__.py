"""The calibration pipeline: the top of the library, the only layer that imports the closed loop and the filters.

:func:`calibrate` runs a method end to end (:mod:`torchcal.pipeline.run`); its steps are the closed loop
(:mod:`~torchcal.pipeline.loop`), the learned stage (:mod:`~torchcal.pipeline.learned`) and the integrated
ANN-EKF (:mod:`~torchcal.pipeline.integrated`); each appends typed records (:mod:`~torchcal.pipeline.records`)
to the :class:`CalibrationRun`.
"""

from torchcal.pipeline.records import EffectRecord, Rejection, StageName
from torchcal.pipeline.run import (
    DEFAULT_METHOD,
    METHODS,
    CalibrationRun,
    Options,
    Stage,
    calibrate,
    check_holdout,
    holdout_split,
    is_trajectory,
    min_poses,
)

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "CalibrationRun",
    "EffectRecord",
    "Options",
    "Rejection",
    "Stage",
    "StageName",
    "calibrate",
    "check_holdout",
    "holdout_split",
    "is_trajectory",
    "min_poses",
]
