"""torchcal: robot arm calibration in PyTorch.

Differentiable float64 robot geometry (DH or URDF) with the instrument pose and probe
lever arm as parameters, named non-geometric effects, a correction network, and the
integrated ANN-EKF of Horvath & Neuner (2024).
"""

import importlib

from torchcal._version import __version__ as __version__  # stated once, in _version.py
from torchcal.errors import (
    EstimationError,
    MeasurementFileError,
    OptionError,
    RobotSpecError,
    ShapeError,
    TorchcalError,
)

# The public names that need torch are imported on first use (PEP 562): `import torchcal` stays light, so the
# command's entry point (torchcal._entry) can catch a Ctrl-C while torch loads and exit cleanly.
_LAZY = {
    "Measurements": "torchcal.data",
    "read_measurements": "torchcal.data",
    "write_measurements": "torchcal.data",
    "Context": "torchcal.effects",
    "CorrectionNet": "torchcal.effects",
    "MeasurementModel": "torchcal.effects",
    "EKFTrainer": "torchcal.filter",
    "RobotModel": "torchcal.robot",
    "load_robot": "torchcal.robot",
    "calibrate": "torchcal.pipeline",  # the pipeline's entry point
    "set_verbosity": "torchcal._console",  # the library's --quiet
}

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
    "set_verbosity",
]


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    if not name.startswith("__"):  # a subpackage not imported yet (torchcal.report, torchcal.sim, ...)
        try:
            return importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"{__name__}.{name}":
                raise
    raise AttributeError(f"module 'torchcal' has no attribute '{name}'")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
