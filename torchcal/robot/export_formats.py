"""Write a robot's calibrated geometry for other software: the UR ROS 2 driver's kinematics file and a DH table.

* :func:`ur_ros2_kinematics` / :func:`ur_ros2_yaml`: the kinematics parameter file that ``ur_calibration`` writes
  and the UR ROS 2 description reads (``ur_description``'s ``ur_macro.xacro``): under a top-level ``kinematics``
  key, per joint ``shoulder, upper_arm, forearm, wrist_1, wrist_2, wrist_3`` its origin ``x, y, z`` [m] and
  ``roll, pitch, yaw`` [rad]. The description builds ``base_link_inertia -> wrist_3_link`` as
  ``prod_i Trans(x, y, z) Rz(yaw) Ry(pitch) Rx(roll) Rz(q_i)``, and ``wrist_3_link -> tool0`` is the identity
  (its two fixed joints, ``rpy (0, -pi/2, -pi/2)`` then ``(pi/2, 0, pi/2)``, cancel). The file is written so that
  this chain is torchcal's ``T_base_flange(q)``: ``base_link_inertia`` is torchcal's base frame and ``tool0`` its
  flange.
* :func:`dh_yaml`: a DH / MDH robot file (CONTRACT section 2, with the calibration's ``beta`` per joint where it is
  not zero) that :func:`torchcal.robot.load_robot` reads back with the same forward kinematics.

Both carry the chain only: the instrument pose, the lever arm and the non-geometric effects stay in the run
directory (report.json; ``torchcal compensate`` applies them).
"""

from __future__ import annotations

import hashlib
import math

import torch

from torchcal.errors import RobotSpecError
from torchcal.robot import transforms as tf
from torchcal.robot.export import exact_rpy
from torchcal.robot.model import DHGeometry, RobotModel

#: The UR description's names of the six joint origins, base to tip.
UR_JOINTS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")

#: How far from exact a transform may be to count as what the UR chain can hold (rounding of float64 products).
EXACT = 1e-12


def _num(x: float) -> str:
    return repr(float(x) + 0.0)  # + 0.0: no '-0.0' in the file


def _axis_frame(axis: torch.Tensor) -> torch.Tensor:
    """A rotation ``A (3, 3)`` whose z column is the unit ``axis (3,)``: ``R_axis(q) = A Rz(q) A^T``."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=axis.dtype, device=axis.device)
    c = float(axis @ z)
    if c > 1 - EXACT:
        return torch.eye(3, dtype=axis.dtype, device=axis.device)
    if c < -1 + EXACT:
        return tf.rot_x(torch.tensor(math.pi, dtype=axis.dtype, device=axis.device))
    v = torch.linalg.cross(z, axis)
    K = tf.skew(v)
    return torch.eye(3, dtype=axis.dtype, device=axis.device) + K + K @ K / (1 + c)  # Rodrigues from z to axis


def _readings_as_signs(robot: RobotModel) -> tuple[torch.Tensor, torch.Tensor]:
    """Per joint the sign ``s`` and offset ``c`` [rad] with model joint ``= s * reading + c``.

    Raises:
        RobotSpecError: the readings map couples joints or scales a reading (the UR driver reads its joints as
            they are; such a map has no place in its file).
    """
    A = robot.readings.matrix().detach().to("cpu", torch.float64)
    b = robot.readings.offset.detach().to("cpu", torch.float64)
    s = torch.diagonal(A) if A.shape[0] == A.shape[1] else torch.zeros(A.shape[0], dtype=A.dtype, device=A.device)
    off_diagonal = (A - torch.diag_embed(s)).abs().max() if A.shape[0] == A.shape[1] else A.new_tensor(1.0)
    if A.shape[0] != A.shape[1] or float(off_diagonal) > EXACT or bool(((s.abs() - 1).abs() > EXACT).any()):
        raise RobotSpecError(
            f"robot '{robot.name}': its readings map (model joint = coupling x reading + offset) is not one reading "
            f"per joint with a sign (coupling {A.tolist()}); the UR kinematics file cannot hold it"
        )
    return s.sign(), b


def ur_chain_origins(robot: RobotModel) -> torch.Tensor:
    """The calibrated chain as the UR description writes it: six joint origins ``(6, 4, 4)`` whose product with
    ``Rz(q_i)`` after each is ``T_base_flange(q)`` for readings ``q``.

    Raises:
        RobotSpecError: not six revolute joints, a readings map that couples or scales, or a flange that is not on
            the last joint's axis (offset from it, or tilted: the description's ``wrist_3_link -> tool0`` is fixed).
    """
    g = robot.geometry
    if g.dof != 6 or any(t != "revolute" for t in g.joint_types):
        raise RobotSpecError(
            f"robot '{robot.name}': the UR kinematics file holds a chain of six revolute joints, this one has "
            f"{g.dof} joints ({', '.join(g.joint_types)})"
        )
    if robot.dof != 6:  # six revolute model joints that fewer or more readings drive: it was 'has 6 joints' alone
        raise RobotSpecError(
            f"robot '{robot.name}': its six revolute joints are driven by {robot.dof} controller readings (a readings "
            "map or mimic joints); the UR kinematics file takes one reading per joint: export --format "
            + ("urdf" if robot.kind == "urdf" else "urdf or dh")
        )
    sign, offset = _readings_as_signs(robot)
    with torch.no_grad():
        O = g.origins().detach().to("cpu", torch.float64).clone()
        axes = g.axes.detach().to("cpu", torch.float64) * sign.unsqueeze(-1)  # R_a(-r) = R_-a(r)
    A = torch.eye(4, dtype=O.dtype, device=O.device).repeat(7, 1, 1)  # A[i]: joint i's z onto its axis; A[6] = I
    for i in range(6):
        A[i, :3, :3] = _axis_frame(axes[i] / axes[i].norm())
        turn = tf.homogeneous(
            A[i, :3, :3] @ tf.rot_z(sign[i] * offset[i]) @ A[i, :3, :3].T,
            torch.zeros(3, dtype=O.dtype, device=O.device),
        )
        O[i] = O[i] @ turn  # R_a(s r + c) = R_a(c) R_sa(r), R_a(c) = R_sa(s c): the offset turns the origin
    out = torch.stack([tf.invert(A[i - 1]) @ O[i] @ A[i] if i else O[i] @ A[i] for i in range(6)])
    tip = tf.invert(A[5]) @ O[6]
    # what follows the last joint must commute with Rz(q6) to move into its origin: a turn about z and a shift along z
    if (
        float((tip[:3, 2] - tip.new_tensor([0.0, 0.0, 1.0])).abs().max()) > EXACT
        or float(tip[:2, 3].abs().max()) > EXACT
    ):
        raise RobotSpecError(
            f"robot '{robot.name}': its flange is off the last joint's axis (offset {tip[:2, 3].tolist()} m, axis "
            f"tilted to {tip[:3, 2].tolist()}); the UR description fixes wrist_3_link -> tool0 and cannot hold it: "
            + ("export --format urdf" if robot.kind == "urdf" else "export --format urdf or dh")
        )
    out[5] = out[5] @ tip
    return out


def ur_ros2_kinematics(robot: RobotModel) -> dict:
    """``{"kinematics": {joint: {x, y, z, roll, pitch, yaw}, "hash": ...}}`` of the calibrated chain
    (:func:`ur_chain_origins`); lengths in m, angles in rad."""
    O = ur_chain_origins(robot)
    block = {}
    for name, T in zip(UR_JOINTS, O):
        roll, pitch, yaw = exact_rpy(T[:3, :3])
        x, y, z = (float(v) for v in T[:3, 3])
        block[name] = {"x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw}
    digest = hashlib.sha256(repr(block).encode()).hexdigest()[:16]
    # the driver compares the hash with the controller's own calibration checksum and warns where they differ: they
    # do, this is another calibration
    block["hash"] = f"calib_torchcal_{digest}"
    return {"kinematics": block}


def ur_ros2_yaml(robot: RobotModel, notes: tuple[str, ...] = ()) -> str:
    """The text of the UR ROS 2 kinematics parameter file (``repr`` floats: they read back to the same float64)."""
    from torchcal._version import __version__

    doc = ur_ros2_kinematics(robot)["kinematics"]
    lines = [f"# UR kinematics parameters of robot '{robot.name}', calibrated by torchcal {__version__}"]
    lines += [f"# {n}" for n in notes]
    lines += ["# base_link_inertia is torchcal's base frame, tool0 its flange", "kinematics:"]
    for name in UR_JOINTS:
        lines.append(f"  {name}:")
        lines += [f"    {k}: {_num(v)}" for k, v in doc[name].items()]
    lines.append(f"  hash: {doc['hash']}")
    return "\n".join(lines) + "\n"


def _dh_joint(robot: RobotModel, i: int, values: torch.Tensor, coms: torch.Tensor | None) -> str:
    """One ``joints:`` entry of :func:`dh_yaml` as a YAML flow mapping."""
    a, alpha, d, theta, beta = (float(v) for v in values[i])
    lo, hi = (float(v) for v in robot.joint_limits[i])
    items = [("a", a), ("alpha", alpha), ("d", d), ("theta", theta)]
    if beta != 0.0:
        items.append(("beta", beta))
    items += [("lower", lo), ("upper", hi)]
    text = ", ".join(f"{k}: {_num(v)}" for k, v in items)
    text += f", type: {robot.geometry.joint_types[i]}, name: {robot.joint_names[i]!r}"
    if coms is not None:
        text += f", mass: {_num(robot.masses[i])}, com: [{', '.join(_num(c) for c in coms[i])}]"
    return "  - {" + text + "}"


def _dh_coms(robot: RobotModel) -> torch.Tensor | None:
    """Centres of mass [m] in DH frame i, as the file gives them (the model keeps them in the frame that turns with
    joint i; for standard DH the two differ by the link's transform, :func:`torchcal.robot.load.load_dh_yaml`)."""
    if not robot.has_masses:
        return None
    coms = robot.coms.detach().to("cpu", torch.float64)
    if robot.geometry.convention.value == "standard":
        M = tf.invert(robot.geometry.origins().detach().to("cpu", torch.float64)[1:])
        coms = (M[:, :3, :3] @ coms.unsqueeze(-1)).squeeze(-1) + M[:, :3, 3]
    return coms


def _readings_lines(robot: RobotModel) -> list[str]:
    if robot.readings.is_identity:
        return []
    A = robot.readings.matrix().detach().to("cpu", torch.float64)
    b = robot.readings.offset.detach().to("cpu", torch.float64)
    rows = ", ".join("[" + ", ".join(_num(v) for v in r) + "]" for r in A)
    lim = robot.limits.detach().to("cpu", torch.float64)
    return [
        "readings:",
        f"  coupling: [{rows}]",
        f"  offset: [{', '.join(_num(v) for v in b)}]",
        f"  lower: [{', '.join(_num(v) for v in lim[:, 0])}]",
        f"  upper: [{', '.join(_num(v) for v in lim[:, 1])}]",
        f"  names: [{', '.join(repr(n) for n in robot.reading_names)}]",
    ]


def dh_yaml(robot: RobotModel, notes: tuple[str, ...] = ()) -> str:
    """A DH / MDH robot file of the calibrated chain that ``--robot`` loads back with the same forward kinematics.

    Raises:
        RobotSpecError: the robot is not a DH robot (a URDF's joint origins are general transforms; export it as a
            URDF).
    """
    from torchcal._version import __version__

    if not isinstance(robot.geometry, DHGeometry):
        raise RobotSpecError(
            f"robot '{robot.name}' is described by a URDF, whose calibrated joint origins a DH table cannot hold; "
            "export --format urdf"
        )
    values = robot.geometry.values.detach().to("cpu", torch.float64)
    lines = [f"# robot '{robot.name}' calibrated by torchcal {__version__}; metres and radians"]
    lines += [f"# {n}" for n in notes]
    lines += [f"name: {robot.name!r}", f"convention: {robot.geometry.convention.value}", "joints:"]
    coms = _dh_coms(robot)
    lines += [_dh_joint(robot, i, values, coms) for i in range(robot.geometry.dof)]
    lines += _readings_lines(robot)
    return "\n".join(lines) + "\n"
