"""torchcal: robot arm calibration in PyTorch.

Differentiable float64 robot geometry (DH or URDF) with the instrument pose and probe
lever arm as parameters, named non-geometric effects, a correction network, and the
integrated ANN-EKF of Horvath & Neuner (2024).
"""

from torchcal.data import Measurements, read_measurements, write_measurements
from torchcal.effects import Context, CorrectionNet, MeasurementModel
from torchcal.errors import (
    EstimationError,
    MeasurementFileError,
    OptionError,
    RobotSpecError,
    ShapeError,
    TorchcalError,
)
from torchcal.filter import EKFTrainer
from torchcal.robot import RobotModel, load_robot

__version__ = "0.1.0"

__all__ = [
    "Context", "CorrectionNet", "EKFTrainer", "MeasurementModel", "Measurements", "read_measurements",
    "write_measurements", "EstimationError", "MeasurementFileError", "OptionError", "RobotModel", "RobotSpecError",
    "ShapeError", "TorchcalError", "load_robot",
]
