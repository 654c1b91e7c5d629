"""Non-geometric effect models: compliance, backlash, cyclic, drift, learned (CorrectionNet)."""

from torchcal.effects.base import Context, Effect, effect_from_config, motion_direction
from torchcal.effects.drift import Drift
from torchcal.effects.joint import Backlash, Compliance, Cyclic, Transmission
from torchcal.effects.kernel import KernelCorrection, fit_kernel_correction
from torchcal.effects.learned import CorrectionNet, LearnedEffect
from torchcal.effects.model import MeasurementModel

#: effect kinds as named in report.json (CONTRACT §4)
KINDS = ("compliance", "backlash", "cyclic", "drift", "learned", "transmission")

__all__ = [
    "KINDS", "Backlash", "Compliance", "Context", "CorrectionNet", "Cyclic", "Drift", "Effect", "KernelCorrection",
    "LearnedEffect", "MeasurementModel", "Transmission", "effect_from_config", "fit_kernel_correction",
    "motion_direction",
]
