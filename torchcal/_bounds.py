"""The ranges an option's value can sensibly take: one place for the library's records and the command line.

A value outside is refused (:class:`~torchcal.errors.OptionError`) before any work: a joint noise of 1e10 degrees
weights every pose to nothing and the fit "passes" its global test; a tracker noise of 1e300 um writes positions of
1e294 m; a rank tolerance of 1e300 leaves no parameter to fit. Each bound is far beyond any real instrument's value
and far below where the arithmetic breaks.
"""

from __future__ import annotations

import math

from torchcal.errors import OptionError

#: tracker noise per axis [m]: a laser tracker is good to micrometres; 1 cm is not a tracker measurement
MAX_SIGMA_TRACKER = 1e-2
#: joint reading noise [rad]: encoders are good to millidegrees; 1 degree is not an encoder reading
MAX_SIGMA_JOINT = math.radians(1.0)
#: the joint reading noise a calibration assumes unless told [rad] (``FitSettings.sigma_joint``): here, not in the
#: pipeline's options, so that the commands that use a finished run read it without importing the pipeline
SIGMA_JOINT = math.radians(0.0005)
#: identifiability tolerance (relative singular value): beyond 1 % the analysis fixes parameters the data determine
MAX_RANK_TOL = 1e-2
#: a known lever arm's elements and sigma [m]: probes sit within a metre or two of the flange; 5 m is mm given as m
MAX_TOOL = 5.0
#: simulated geometric biases: lengths [m] and angles [rad]
MAX_SIGMA_LENGTH = 0.01
MAX_SIGMA_ANGLE = math.radians(1.0)
#: the largest payload a row may carry [kg]: beyond it the number is in grams (or a typo); the heaviest industrial
#: arms carry about 2.3 t. The measurement files' payload column, compensate --payload and simulate's payloads
MAX_PAYLOAD_KG = 3000.0
#: simulated torque noise [N m]: drives measure torques to a fraction of a N m; 1000 N m is no measurement
MAX_SIGMA_TORQUE = 1e3


def check_range(
    name: str, value: float, low: float, high: float, *, low_open: bool = False, scale: float = 1.0, unit: str = ""
) -> None:
    """Raise :class:`OptionError` unless ``low <= value <= high`` (``low < value`` with ``low_open``).

    ``scale`` and ``unit`` say how the message shows the numbers (e.g. ``1e6, 'um'`` for metres shown as um).
    """
    ok = math.isfinite(value) and (low < value if low_open else low <= value) and value <= high
    if not ok:
        u = f" {unit}" if unit else ""
        left = "(" if low_open else "["
        raise OptionError(f"{name} must lie in {left}{low * scale:g}, {high * scale:g}]{u}, got {value * scale:g}{u}")
