"""torchcal: robot arm calibration in PyTorch.

Differentiable float64 robot geometry (DH or URDF) with the instrument pose and probe
lever arm as parameters, named non-geometric effects, a correction network, and the
integrated ANN-EKF of Horvath & Neuner (2024).
"""

from torchcal._version import __version__ as __version__  # stated once, in _version.py
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

__all__ = [
    "Context",
    "CorrectionNet",
    "EKFTrainer",
    "MeasurementModel",
    "Measurements",
    "read_measurements",
    "write_measurements",
    "EstimationError",
    "MeasurementFileError",
    "OptionError",
    "RobotModel",
    "RobotSpecError",
    "ShapeError",
    "TorchcalError",
    "load_robot",
]


def __getattr__(name: str):
    # torchcal.calibrate, the pipeline's entry point, imported on first use: `import torchcal` stays light
    if name == "calibrate":
        from torchcal.pipeline import calibrate

        return calibrate
    raise AttributeError(f"module 'torchcal' has no attribute '{name}'")
