"""Exporting a finished run to the files other software reads: the calibrated URDF, the UR ROS 2 driver's kinematics
parameter file (``ur-ros2``) and a DH / MDH robot file that ``--robot`` loads back (``dh``).

Each carries the geometry, the lever arm and the tracker pose; none can carry the non-geometric effects, which every
file names in its header (:func:`left_out`), since commanding the robot with them needs ``torchcal compensate``.
"""

from __future__ import annotations

from pathlib import Path

from torchcal.effects.model import MeasurementModel
from torchcal.robot.export import write_text, write_urdf
from torchcal.robot.export_formats import dh_yaml, ur_ros2_yaml
from torchcal.use.rundir import load_model

#: the formats ``torchcal export --format`` writes
FORMATS = ("ur-ros2", "dh", "urdf")


def left_out(model: MeasurementModel) -> list[str]:
    """Labels of the model's parts that a robot file (geometry, lever arm, tracker pose only) cannot carry."""
    return [e.label() for e in model.effects]


def export_run(run: str | Path, fmt: str, out_file: Path) -> None:
    """Write the calibrated robot of the run directory ``run`` as ``fmt`` (one of :data:`FORMATS`) to ``out_file``.

    A format the robot cannot be written in (``ur-ros2`` of a robot that is not a UR arm) is refused before any
    folder is made; ``out_file``'s folder is made as ``predict`` and ``plan`` make theirs.
    """
    if fmt not in FORMATS:
        raise ValueError(f"export format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    model, _ = load_model(run)
    left = left_out(model)
    notes = (f"NOT in this file: {', '.join(left)} (torchcal compensate {run} applies them)",) if left else ()
    text = None
    if fmt != "urdf":
        write = ur_ros2_yaml if fmt == "ur-ros2" else dh_yaml
        text = f"# written_by: torchcal export\n{write(model.robot, notes)}"
    out_file.parent.mkdir(parents=True, exist_ok=True)
    if text is None:
        write_urdf(model.robot, out_file, notes=list(notes))
    else:
        write_text(out_file, text)


__all__ = ["FORMATS", "export_run", "left_out"]
