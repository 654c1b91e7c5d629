"""Prismatic joints: known answers, pytorch-kinematics, exact Jacobians, gravity, the loaders' checks."""

import math

import pytest
import torch

import torchcal
from torchcal.errors import RobotSpecError
from torchcal.estimate.check import check_jacobian
from torchcal.robot import transforms as tf

F64 = torch.float64

# a SCARA-like arm in standard DH: two revolute joints, a vertical prismatic quill (gravity along its axis), a wrist
SCARA = """name: scara
convention: standard
joints:
  - {a: 0.4, alpha: 0.0, d: 0.3, theta: 0.1, mass: 5.0, com: [-0.2, 0.0, 0.0]}
  - {a: 0.3, alpha: 3.141592653589793, d: 0.0, theta: 0.0, mass: 3.0, com: [-0.1, 0.0, 0.0]}
  - {type: prismatic, a: 0.0, alpha: 0.0, d: 0.05, theta: 0.2, lower: 0.0, upper: 0.3, mass: 1.5, com: [0.0, 0.0, 0.1]}
  - {a: 0.0, alpha: 0.0, d: 0.1, theta: 0.0, mass: 0.5, com: [0.0, 0.0, 0.02]}
"""

# a URDF: a tilted linear axis, then two revolute joints
_INERTIA = '<inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/>'
URDF = f"""<robot name="slide">
  <link name="base"/>
  <link name="carriage"><inertial><mass value="4.0"/>{_INERTIA}</inertial></link>
  <link name="arm"><inertial><origin xyz="0.2 0 0"/><mass value="2.0"/>{_INERTIA}</inertial></link>
  <link name="forearm"><inertial><origin xyz="0.1 0 0"/><mass value="1.0"/>{_INERTIA}</inertial></link>
  <link name="tool"/>
  <joint name="slide" type="prismatic"><parent link="base"/><child link="carriage"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.2 -0.3 0.1"/><axis xyz="0.6 0 0.8"/>
    <limit lower="-0.5" upper="1.5" effort="1" velocity="1"/></joint>
  <joint name="shoulder" type="revolute"><parent link="carriage"/><child link="arm"/>
    <origin xyz="0 0 0.2" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="elbow" type="continuous"><parent link="arm"/><child link="forearm"/>
    <origin xyz="0.4 0 0" rpy="0 0 0.5"/><axis xyz="0 0 1"/></joint>
  <joint name="tool_joint" type="fixed"><parent link="forearm"/><child link="tool"/><origin xyz="0.3 0 0.05"/></joint>
</robot>
"""


@pytest.fixture
def scara(tmp_path):
    path = tmp_path / "scara.yaml"
    path.write_text(SCARA)
    return torchcal.load_robot(path)


@pytest.fixture
def slide(tmp_path):
    path = tmp_path / "slide.urdf"
    path.write_text(URDF)
    return torchcal.load_robot(path)


def random_q(robot, n, seed=0):
    g = torch.Generator().manual_seed(seed)
    lo, hi = robot.limits[:, 0].clamp(min=-math.pi), robot.limits[:, 1].clamp(max=math.pi)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)


def perturbed(robot, seed=1):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        robot.geometry.delta.normal_(0.0, 1e-2, generator=g)
        robot.instrument.nominal.copy_(
            tf.homogeneous(
                tf.rpy_to_matrix(torch.tensor([0.3, -0.2, 2.0], dtype=F64)), torch.tensor([2.5, -1.0, 0.4], dtype=F64)
            )
        )
        robot.instrument.delta.normal_(0.0, 1e-2, generator=g)
        robot.tool.nominal.copy_(torch.tensor([0.01, -0.02, 0.15], dtype=F64))
        robot.tool.delta.normal_(0.0, 1e-2, generator=g)
    return robot


def test_track_robot_is_the_ur10_moved_along_the_track():
    # known answer: T_base_flange(q) = Ty(q1) Tz(0.25) T_ur10(q2..q7), to rounding
    track, ur10 = torchcal.load_robot("ur10_track"), torchcal.load_robot("ur10")
    assert track.joint_types == ("prismatic",) + ("revolute",) * 6
    assert track.limits[0].tolist() == [-1.0, 1.0]  # metres
    q = random_q(track, 100)
    zero = torch.zeros(100, dtype=F64)
    lift = tf.translation(torch.stack([zero, q[:, 0], zero + 0.25], -1))
    with torch.no_grad():
        assert (track(q) - lift @ ur10(q[:, 1:])).abs().max() < 1e-14
        # the UR10's gravity torques are the same on the track; the horizontal track carries no weight along itself
        tau = track.gravity_torques(q)
        assert (tau[:, 1:] - ur10.gravity_torques(q[:, 1:])).abs().max() < 1e-12
        assert tau[:, 0].abs().max() < 1e-12


def test_dh_prismatic_reading_adds_to_d(scara):
    q = random_q(scara, 20, seed=2)
    moved = scara.geometry.nominal.clone()
    with torch.no_grad():
        for qi, T in zip(q, scara(q)):
            table = moved.clone()
            table[[0, 1, 3], 3] += qi[[0, 1, 3]]  # revolute: reading + theta
            table[2, 2] += qi[2]  # prismatic: reading + d, theta fixed
            scara.geometry.set_values(table)
            fixed = scara(torch.zeros(1, 4, dtype=F64))[0]
            assert (fixed - T).abs().max() < 1e-15
            scara.reset_parameters()


@pytest.mark.parametrize("name", ["scara", "slide", "track"])
def test_fk_equals_pytorch_kinematics(name, scara, slide):
    robot = {"scara": scara, "slide": slide, "track": None}[name] or torchcal.load_robot("ur10_track")
    perturbed(robot)
    q = random_q(robot, 50, seed=3)
    with torch.no_grad():
        T = robot(q)
    T_pk = robot.chain.forward_kinematics(q).get_matrix()
    assert (T - T_pk).abs().max() < 1e-14


def test_urdf_prismatic_joint_matches_pytorch_kinematics_parser(slide):
    import pytorch_kinematics as pk

    chain = pk.build_serial_chain_from_urdf(URDF.encode(), "tool", "base")
    q = random_q(slide, 30, seed=4)
    with torch.no_grad():
        T = slide(q)
    assert slide.joint_types == ("prismatic", "revolute", "revolute")
    assert slide.limits[0].tolist() == [-0.5, 1.5]
    assert (chain.forward_kinematics(q.float()).get_matrix().double() - T).abs().max() < 1e-6  # pk parses in float32


@pytest.mark.parametrize("name", ["scara", "slide", "track"])
def test_probe_jacobian_equals_autograd(name, scara, slide):
    robot = perturbed({"scara": scara, "slide": slide, "track": None}[name] or torchcal.load_robot("ur10_track"))
    q = random_q(robot, 10, seed=5)
    _, J = robot.probe_jacobian(q)
    J_ad = torch.func.vmap(torch.func.jacrev(lambda x: robot.probe_in_base(x[None])[0]))(q)
    assert (J - J_ad).abs().max() < 1e-13


@pytest.mark.parametrize("name", ["scara", "slide", "track"])
def test_tracker_jacobian_matches_central_differences(name, scara, slide):
    robot = perturbed({"scara": scara, "slide": slide, "track": None}[name] or torchcal.load_robot("ur10_track"))
    q = random_q(robot, 8, seed=6)
    for group, grp in robot.groups().items():
        cols = [(group, i) for i in range(grp.delta.numel())]
        p, J = robot.tracker_jacobian(q, cols)
        d0 = grp.delta.detach().clone()

        def f(x, grp=grp, d0=d0):
            with torch.no_grad():
                grp.delta.copy_(x.reshape(d0.shape))
                out = robot.probe_position(q).reshape(-1)
                grp.delta.copy_(d0)
            return out

        assert check_jacobian(f, d0.flatten(), J.reshape(-1, len(cols))) < 1e-7, group
        assert (p - robot.probe_position(q)).abs().max() < 1e-14


@pytest.mark.parametrize("name", ["scara", "slide"])
def test_gravity_force_is_minus_gradient_of_potential(name, scara, slide):
    robot = perturbed({"scara": scara, "slide": slide}[name])
    q = random_q(robot, 10, seed=7).requires_grad_(True)
    F, T = robot.joint_frames(q)
    p = tf.transform_points(T, robot.t_flange_probe())
    V = (robot.masses * 9.80665 * tf.transform_points(F, robot.coms)[..., 2]).sum() + (2.0 * 9.80665 * p[..., 2]).sum()
    (dV,) = torch.autograd.grad(V, q)
    tau = robot.gravity_torques(q.detach(), payload=2.0)
    assert torch.allclose(tau, -dV, atol=1e-10, rtol=0)
    j = robot.joint_types.index("prismatic")
    assert tau[:, j].abs().min() > 1.0  # [N]: the quill and the tilted slide carry weight along their axes


def test_all_revolute_robots_keep_their_joint_types():
    for name in ("ur5", "ur5.urdf", "panda"):
        robot = torchcal.load_robot(name)
        assert robot.joint_types == ("revolute",) * robot.dof and not robot.prismatic.any()
        assert "geometry.prismatic" not in robot.state_dict()  # run directories written before still load


def test_loader_checks_the_type(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(SCARA.replace("type: prismatic", "type: linear"))
    with pytest.raises(RobotSpecError, match="type 'linear' is not one of revolute, prismatic"):
        torchcal.load_robot(bad)
    default = tmp_path / "default.yaml"
    default.write_text(SCARA.replace("lower: 0.0, upper: 0.3, ", ""))
    assert torchcal.load_robot(default).limits[2].tolist() == [-10.0, 10.0]  # m
