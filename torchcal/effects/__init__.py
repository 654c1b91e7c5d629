"""Non-geometric effect models: compliance, backlash, cyclic, drift, learned (CorrectionNet)."""

from torchcal.effects.base import Acts, Context, Effect, motion_direction
from torchcal.effects.drift import Drift
from torchcal.effects.gp import GPCorrection, GPSettings, fit_gp_correction
from torchcal.effects.instrument import TrackerError
from torchcal.effects.joint import (
    MAX_JOINT_ERROR,
    Backlash,
    Compliance,
    Coupling,
    Cyclic,
    LumpedCompliance,
    TorqueCompliance,
    Transmission,
    joint_function_check,
)
from torchcal.effects.kernel import KernelCorrection, fit_kernel_correction
from torchcal.effects.learned import CorrectionNet, LearnedEffect
from torchcal.effects.model import MeasurementModel
from torchcal.effects.registry import KINDS, NAMED_KINDS, effect_from_config

__all__ = [
    "KINDS",
    "NAMED_KINDS",
    "Acts",
    "Backlash",
    "Compliance",
    "Context",
    "CorrectionNet",
    "Cyclic",
    "Drift",
    "Effect",
    "KernelCorrection",
    "LearnedEffect",
    "MeasurementModel",
    "effect_from_config",
    "fit_kernel_correction",
    "motion_direction",
]
__all__ += ["GPCorrection", "GPSettings", "Transmission", "fit_gp_correction", "joint_function_check"]
__all__ += ["MAX_JOINT_ERROR", "Coupling", "LumpedCompliance", "TorqueCompliance", "TrackerError"]
