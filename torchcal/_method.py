"""The calibration methods and the integrated method's engines, declared once.

The parser, the options and the table of stages all read them here. A leaf without torch, so that the command
line's parser is built before torch loads. Each member is its own name as a string (``Method.AUTO == "auto"``),
so report.json and the command line keep the names they always had.
"""

import enum


class Method(str, enum.Enum):
    """A calibration method (docs/methods.md); :data:`torchcal.pipeline.methods.METHOD_TABLE` holds its stages."""

    AUTO = "auto"  # the default: geometry, the closed loop of named effects, then a learned correction
    KINEMATIC = "kinematic"  # geometry alone
    PCM = "pcm"  # the nominal geometry and the paper's position correction model
    KINEMATIC_ANN = "kinematic+ann"  # geometry, then a correction network on its residuals
    INTEGRATED = "integrated"  # the seed paper's integrated filter

    def __str__(self) -> str:
        return self.value


class Engine(str, enum.Enum):
    """An engine of the integrated method (:mod:`torchcal.pipeline.integrated`)."""

    AUTO = "auto"  # chosen on validation among the engines and their settings, geometry alone a candidate
    ADAPTIVE = "adaptive"  # geometry in the filter state
    EKF = "ekf"  # the paper's filter

    def __str__(self) -> str:
        return self.value


DEFAULT_METHOD = Method.AUTO
#: the methods' and the engines' names, in their declared order
METHODS: tuple[str, ...] = tuple(m.value for m in Method)
ENGINES: tuple[str, ...] = tuple(e.value for e in Engine)


#: the models a run may predict (or command) a row with, by the names of predict's and compensate's ``model`` column
#: and in its order: the run's model, its kinematic calibration, its geometry and physical effects alone, the nominal
#: geometry with the fitted instrument pose and lever arm (:mod:`torchcal.pipeline.beyond`)
CANDIDATES = ("full", "geometric", "physical", "nominal")
