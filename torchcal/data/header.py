"""A measurement file's ``# robot:`` line checked against the robot it is read for."""

from __future__ import annotations

from pathlib import Path

from torchcal.errors import MeasurementFileError


def robot_key(name: str) -> str:
    """A robot's name as compared: without directory, extension and case."""
    n = Path(str(name).strip()).name.lower()
    for ext in (".urdf", ".yaml", ".yml"):
        if n.endswith(ext):
            n = n[: -len(ext)]
    return n


def check_header_robot(data, spec: str, robot, described: str) -> None:
    """Refuse a file whose ``# robot:`` line names another robot than the one it is read for.

    A mismatch would otherwise be "calibrated" away as huge geometric corrections. Names are compared
    without directory, extension and case (``ur5``, ``robots/ur5.urdf`` and a URDF named ``UR5`` agree).

    Args:
        data: the measurements (``data.meta['robot']`` is the file's line).
        spec: the robot as given (built-in name or file path); robot: the loaded robot.
        described: how the message names it, e.g. ``--robot ur5``.
    """
    named = data.meta.get("robot")
    if not named:
        return
    ours = {robot_key(spec), robot_key(robot.name)}
    if robot_key(named) not in ours:
        raise MeasurementFileError(
            data.source,
            f"the file's '# robot: {named}' line names another robot than {described} ('{robot.name}')",
            hint="pass the robot the data were measured with, or correct the '# robot:' "
            "line if the name differs but the robot is the same",
        )
