"""Export to other software: the UR ROS 2 kinematics file built as the UR description builds it, and a DH table
that ``--robot`` loads back, both with the calibrated forward kinematics to 1e-9 m."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import torchcal
from torchcal.errors import RobotSpecError
from torchcal.robot.export_formats import UR_JOINTS, dh_yaml, ur_ros2_kinematics

F64 = torch.float64
FANUC = str(Path(__file__).resolve().parent / "data" / "fanuc_like.yaml")


def random_q(robot, n=1000, seed=0):
    g = torch.Generator().manual_seed(seed)
    lo, hi = robot.limits[:, 0].clamp(min=-math.pi), robot.limits[:, 1].clamp(max=math.pi)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)


def calibrated(name, seed=1, size=2e-3, keep_tip=True):
    """``name`` with random corrections on every free geometry element (the flange's a, alpha kept when
    ``keep_tip``: a UR's flange sits on its last axis) and its joint-zero offsets."""
    robot = torchcal.load_robot(name)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        d = torch.randn(robot.geometry.delta.shape, generator=g, dtype=F64) * size
        robot.geometry.delta.copy_(d * robot.geometry.mask)
        if keep_tip and robot.kind == "dh":
            robot.geometry.delta[-1, [0, 1, 4]] = 0.0
    return robot


def _rpy(roll, pitch, yaw):
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def ur_description_fk(kinematics: dict, q: np.ndarray) -> np.ndarray:
    """base_link_inertia -> tool0 ``(N, 4, 4)`` as ur_description's ur_macro.xacro builds it: per joint an origin
    ``xyz`` + ``rpy`` from the file, then a turn about local z by q; wrist_3_link -> flange -> tool0 (rpy
    (0, -pi/2, -pi/2), then (pi/2, 0, pi/2))."""
    out = np.zeros((len(q), 4, 4))
    for n, qn in enumerate(q):
        T = np.eye(4)
        for k, joint in enumerate(UR_JOINTS):
            j = kinematics[joint]
            O = np.eye(4)
            O[:3, :3], O[:3, 3] = _rpy(j["roll"], j["pitch"], j["yaw"]), [j["x"], j["y"], j["z"]]
            Rz = np.eye(4)
            Rz[:3, :3] = _rpy(0.0, 0.0, qn[k])
            T = T @ O @ Rz
        for rpy in ((0.0, -math.pi / 2, -math.pi / 2), (math.pi / 2, 0.0, math.pi / 2)):
            F = np.eye(4)
            F[:3, :3] = _rpy(*rpy)
            T = T @ F
        out[n] = T
    return out


@pytest.mark.parametrize("name", ["ur5", "ur10", "ur5.urdf"])
def test_ur_ros2_file_built_as_the_ur_description_reproduces_the_calibration(name, tmp_path):
    robot = calibrated(name)
    text = yaml.safe_dump(ur_ros2_kinematics(robot))
    doc = yaml.safe_load(text)
    assert sorted(doc) == ["kinematics"] and set(UR_JOINTS) <= set(doc["kinematics"])
    assert all(sorted(doc["kinematics"][j]) == ["pitch", "roll", "x", "y", "yaw", "z"] for j in UR_JOINTS)
    q = random_q(robot)
    ours = robot(q).detach().numpy()
    theirs = ur_description_fk(doc["kinematics"], q.numpy())
    assert np.abs(theirs[:, :3, 3] - ours[:, :3, 3]).max() < 1e-9  # m
    assert np.abs(theirs[:, :3, :3] - ours[:, :3, :3]).max() < 1e-9  # rad, the flange's orientation too


def test_ur_ros2_refuses_what_the_ur_description_cannot_hold():
    with pytest.raises(RobotSpecError, match="six revolute joints"):
        ur_ros2_kinematics(torchcal.load_robot("panda"))
    robot = calibrated("ur5", keep_tip=False)  # the flange moved off joint 6's axis
    with pytest.raises(RobotSpecError, match="off the last joint's axis"):
        ur_ros2_kinematics(robot)


@pytest.mark.parametrize("name", ["ur5", "ur10_track", FANUC])
def test_dh_file_loads_back_with_the_same_forward_kinematics(name, tmp_path):
    robot = calibrated(name, keep_tip=False)
    assert robot.geometry.delta[:, 4].abs().max() > 0  # beta is written where the calibration has one
    path = tmp_path / "cal.yaml"
    path.write_text(dh_yaml(robot, notes=("a note",)), encoding="utf-8")
    back = torchcal.load_robot(path)
    q = random_q(robot)
    assert float((back(q) - robot(q)).detach().abs().max()) < 1e-9
    assert back.joint_names == robot.joint_names and torch.equal(back.limits, robot.limits)
    if robot.has_masses:
        assert float((back.coms - robot.coms).abs().max()) < 1e-12
        assert torch.equal(back.masses, robot.masses)
    with pytest.raises(RobotSpecError, match="export --format urdf"):
        dh_yaml(torchcal.load_robot("ur5.urdf"))
