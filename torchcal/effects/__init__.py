"""Non-geometric effect models: compliance, backlash, cyclic, drift, learned (CorrectionNet)."""

from torchcal.effects.base import Context, Effect, effect_from_config, motion_direction
from torchcal.effects.drift import Drift
from torchcal.effects.gp import GPCorrection, GPSettings, fit_gp_correction
from torchcal.effects.joint import Backlash, Compliance, Cyclic
from torchcal.effects.kernel import KernelCorrection, fit_kernel_correction
from torchcal.effects.learned import CorrectionNet, LearnedEffect
from torchcal.effects.model import MeasurementModel

#: effect kinds as named in report.json (CONTRACT §4)
KINDS = ("compliance", "backlash", "cyclic", "drift", "learned")

__all__ = [
    "KINDS", "Backlash", "Compliance", "Context", "CorrectionNet", "Cyclic", "Drift", "Effect", "KernelCorrection",
    "LearnedEffect", "MeasurementModel", "effect_from_config", "fit_kernel_correction", "motion_direction",
]
__all__ += ["GPCorrection", "GPSettings", "fit_gp_correction"]
