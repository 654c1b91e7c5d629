"""Robot descriptions (DH / URDF) -> differentiable float64 geometry + a pytorch-kinematics chain."""

from torchcal.robot.export import write_urdf
from torchcal.robot.load import builtin_robots, load_dh_yaml, load_robot, load_urdf, resolve_robot_spec
from torchcal.robot.model import (
    DHConvention,
    DHGeometry,
    Instrument,
    ParameterInfo,
    RobotModel,
    Tool,
    URDFGeometry,
)

__all__ = [
    "DHConvention",
    "DHGeometry",
    "Instrument",
    "ParameterInfo",
    "RobotModel",
    "Tool",
    "URDFGeometry",
    "builtin_robots",
    "load_dh_yaml",
    "load_robot",
    "load_urdf",
    "resolve_robot_spec",
    "write_urdf",
]
