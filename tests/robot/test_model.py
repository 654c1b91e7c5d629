"""Robot model: known answers, independent DH, pytorch-kinematics, gradients, gravity torques."""

import copy
import math

import numpy as np
import pytest
import torch

import torchcal

# the independent numpy standard DH and UR's tables (one copy, also behind scripts/fk_agreement.py)
from experiments.fk_agreement import UR_DH, numpy_standard_dh
from torchcal.errors import RobotSpecError, ShapeError
from torchcal.robot import transforms as tf

F64 = torch.float64


def numpy_modified_dh(table, q):
    """Craig's modified DH: rows (a_{i-1}, alpha_{i-1}, d_i)."""
    out = []
    for qq in q:
        T = np.eye(4)
        for (a, al, d), th in zip(table, qq):
            ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
            T = T @ np.array(
                [[ct, -st, 0, a], [st * ca, ct * ca, -sa, -sa * d], [st * sa, ct * sa, ca, ca * d], [0, 0, 0, 1]]
            )
        out.append(T)
    return np.stack(out)


def random_q(robot, n, seed=0):
    g = torch.Generator().manual_seed(seed)
    lo, hi = robot.limits[:, 0].clamp(min=-math.pi), robot.limits[:, 1].clamp(max=math.pi)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)


@pytest.mark.parametrize("name", ["ur5", "ur10"])
def test_ur_matches_independent_standard_dh(name):
    robot = torchcal.load_robot(name)
    q = random_q(robot, 200)
    with torch.no_grad():
        T = robot(q).numpy()
    ref = numpy_standard_dh(UR_DH[name], q.numpy())
    assert T.dtype == np.float64
    assert np.abs(T - ref).max() < 1e-12


def test_ur5_zero_pose_known_answer():
    # UR5 stretched out at q = 0: flange at (a2 + a3, -(d4 + d6), d1 - d5), z axis along -y
    robot = torchcal.load_robot("ur5")
    T = robot(torch.zeros(1, 6, dtype=F64))[0].detach()
    expected = torch.tensor([-0.425 - 0.39225, -(0.10915 + 0.0823), 0.089159 - 0.09465], dtype=F64)
    assert torch.allclose(T[:3, 3], expected, atol=1e-15, rtol=0)
    assert torch.allclose(T[:3, 2], torch.tensor([0.0, -1.0, 0.0], dtype=F64), atol=1e-15)


def test_planar_two_link_known_answer(tmp_path):
    spec = tmp_path / "planar.yaml"
    spec.write_text(
        "name: planar\nconvention: standard\njoints:\n"
        "  - {a: 1.0, alpha: 0.0, d: 0.0, theta: 0.0}\n"
        "  - {a: 0.5, alpha: 0.0, d: 0.0, theta: 0.0}\n"
    )
    robot = torchcal.load_robot(spec)
    q = torch.tensor([[math.pi / 2, -math.pi / 2], [0.0, math.pi]], dtype=F64)
    p = robot(q)[:, :3, 3].detach()
    assert torch.allclose(p, torch.tensor([[0.5, 1.0, 0.0], [0.5, 0.0, 0.0]], dtype=F64), atol=1e-15)


def test_modified_dh_matches_craig(tmp_path):
    table = [
        (0.0, 0.0, 0.333),
        (0.0, -math.pi / 2, 0.0),
        (0.0, math.pi / 2, 0.316),
        (0.0825, math.pi / 2, 0.0),
        (-0.0825, -math.pi / 2, 0.384),
        (0.0, math.pi / 2, 0.0),
        (0.088, math.pi / 2, 0.0),
    ]
    rows = "".join(f"  - {{a: {a!r}, alpha: {al!r}, d: {d!r}, theta: 0.0}}\n" for a, al, d in table)
    spec = tmp_path / "arm7.yaml"
    spec.write_text(f"name: arm7\nconvention: modified\njoints:\n{rows}")
    robot = torchcal.load_robot(spec)
    q = random_q(robot, 50, seed=3)
    with torch.no_grad():
        T = robot(q).numpy()
    assert np.abs(T - numpy_modified_dh(table, q.numpy())).max() < 1e-12


@pytest.mark.parametrize("spec", ["ur5", "ur10", "ur5.urdf", "panda"])
def test_fk_equals_pytorch_kinematics(spec):
    robot = torchcal.load_robot(spec)
    q = random_q(robot, 100, seed=1)
    # also with non-zero corrections: the pk chain follows the calibrated geometry
    torch.manual_seed(0)
    with torch.no_grad():
        robot.geometry.delta.normal_(0.0, 1e-3)
        T = robot(q)
    chain = robot.chain
    T_pk = chain.forward_kinematics(q).get_matrix()
    assert T_pk.dtype == F64
    assert (T_pk - T).abs().max().item() < 1e-12


def test_ur5_dh_and_urdf_agree_up_to_fixed_frames():
    dh = torchcal.load_robot("ur5")
    urdf = torchcal.load_robot("ur5.urdf")
    assert urdf.kind == "urdf" and urdf.tip_link == "tool0" and urdf.base_link == "base_link"
    q = random_q(dh, 100, seed=2)
    with torch.no_grad():
        T_dh, T_urdf = dh(q), urdf(q)
    # ROS base_link is the DH base frame turned by pi about z; tool0 is DH frame 6
    Rz = tf.homogeneous(tf.rot_z(torch.tensor(math.pi, dtype=F64)), torch.zeros(3, dtype=F64))
    assert (Rz @ T_dh - T_urdf).abs().max().item() < 1e-12


def test_panda_urdf_and_modified_dh_agree():
    urdf = torchcal.load_robot("panda.urdf")
    dh = torchcal.load_robot("panda.yaml")
    assert urdf.dof == dh.dof == 7
    q = random_q(urdf, 50, seed=4)
    with torch.no_grad():
        T_u, T_d = urdf(q), dh(q)
    # panda_link8 (the flange) is 0.107 m along z of DH frame 7
    flange = tf.translation(torch.tensor([0.0, 0.0, 0.107], dtype=F64))
    assert (T_d @ flange - T_u).abs().max().item() < 1e-12


def _set_random(robot, scale=1e-3, seed=0):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for grp in robot.groups().values():
            grp.delta.copy_(scale * torch.randn(grp.delta.shape, generator=g, dtype=F64))
        robot.tool.nominal.copy_(torch.tensor([0.01, -0.02, 0.1], dtype=F64))
        robot.instrument.nominal.copy_(tf.se3_from_vector(torch.tensor([2.0, 1.0, -0.5, 0.1, -0.2, 2.5], dtype=F64)))


@pytest.mark.parametrize("spec", ["ur5", "panda.urdf"])
@pytest.mark.parametrize("group", ["geometry", "instrument", "tool"])
def test_gradcheck_every_group(spec, group):
    robot = torchcal.load_robot(spec)
    _set_random(robot)
    q = random_q(robot, 4, seed=5)
    param = robot.groups()[group].delta

    def f(delta):
        return torch.func.functional_call(_ProbeWrapper(robot), {f"robot.{group}.delta": delta}, (q,))

    assert torch.autograd.gradcheck(f, (param.detach().clone().requires_grad_(True),), eps=1e-6, atol=1e-8)


class _ProbeWrapper(torch.nn.Module):
    def __init__(self, robot):
        super().__init__()
        self.robot = robot

    def forward(self, q):
        return self.robot.probe_position(q)


@pytest.mark.parametrize("spec", ["ur5", "ur10", "panda.urdf", "panda"])
def test_every_group_receives_a_nonzero_gradient(spec):
    # pytorch-kinematics drops gradients of its offsets; torchcal must not
    robot = torchcal.load_robot(spec)
    _set_random(robot, seed=1)
    q = random_q(robot, 20, seed=6)
    robot.probe_position(q).square().sum().backward()
    for name, grp in robot.groups().items():
        g = grp.delta.grad
        assert g is not None, name
        assert torch.isfinite(g).all(), name
        # every free element moves the probe somewhere in 20 random poses
        assert (g[grp.mask].abs() > 0).all(), (name, g)


def test_gravity_torque_is_minus_gradient_of_potential():
    robot = torchcal.load_robot("ur10")
    q = random_q(robot, 10, seed=7).requires_grad_(True)
    F, _ = robot.joint_frames(q)
    com = tf.transform_points(F, robot.coms)
    V = (robot.masses * 9.80665 * com[..., 2]).sum()
    (dV,) = torch.autograd.grad(V, q)
    tau = robot.gravity_torques(q.detach())
    assert torch.allclose(tau, -dV, atol=1e-10, rtol=0)
    # and a payload at the probe adds its own potential
    with torch.no_grad():
        robot.tool.nominal.copy_(torch.tensor([0.0, 0.0, 0.1], dtype=F64))
    q2 = q.detach().clone().requires_grad_(True)
    F, T = robot.joint_frames(q2)
    p = tf.transform_points(T, robot.t_flange_probe())
    V = (robot.masses * 9.80665 * tf.transform_points(F, robot.coms)[..., 2]).sum() + (2.0 * 9.80665 * p[..., 2]).sum()
    (dV,) = torch.autograd.grad(V, q2)
    assert torch.allclose(robot.gravity_torques(q2.detach(), payload=2.0), -dV, atol=1e-10, rtol=0)


def test_static_torques_are_reused_for_the_same_joint_tensor_and_geometry():
    robot = torchcal.load_robot("ur10")
    q = random_q(robot, 20, seed=9)
    tau = robot.static_torques(q)
    assert torch.equal(tau, robot.gravity_torques(q)) and not tau.requires_grad
    assert robot.static_torques(q) is tau  # the same tensor and geometry again: the result is reused
    assert robot.static_torques(q.clone()) is not tau
    with torch.no_grad():  # another geometry (by value): computed again, as gravity_torques gives it
        robot.geometry.delta.add_(1e-3 * torch.randn(robot.geometry.delta.shape, dtype=F64))
    moved = robot.static_torques(q)
    assert moved is not tau and torch.equal(moved, robot.gravity_torques(q).detach())
    assert not torch.equal(moved, tau)
    q.add_(0.1)  # changed in place: computed again
    again = robot.static_torques(q)
    assert again is not moved and torch.equal(again, robot.gravity_torques(q).detach())
    # with a payload the lever arm enters, and a moved lever arm is seen
    with_payload = robot.static_torques(q, payload=2.0)
    with torch.no_grad():
        robot.tool.delta.add_(torch.tensor([0.0, 0.0, 0.05], dtype=F64))
    shifted = robot.static_torques(q, payload=2.0)
    assert shifted is not with_payload and torch.equal(shifted, robot.gravity_torques(q, payload=2.0).detach())
    # under a transform the torque is computed and not cached
    count = len(robot._torque_cache)
    value = torch.func.jvp(lambda x: robot.static_torques(x), (q,), (torch.ones_like(q),))[0]
    assert torch.equal(value, again) and len(robot._torque_cache) == count
    copied = copy.deepcopy(robot)  # a copy starts without the cache and fills its own
    assert "_torque_cache" not in copied.__dict__
    assert torch.equal(copied.static_torques(q), again) and len(robot._torque_cache) == count


def test_urdf_masses_match_dh_masses():
    dh, urdf = torchcal.load_robot("ur10"), torchcal.load_robot("ur10.urdf")
    assert torch.allclose(dh.masses, urdf.masses)
    q = random_q(dh, 10, seed=8)
    assert torch.allclose(dh.gravity_torques(q), urdf.gravity_torques(q), atol=1e-9)


def test_float32_and_bad_shapes_are_errors():
    robot = torchcal.load_robot("ur5")
    with pytest.raises(ShapeError, match="float32.*float64"):
        robot(torch.zeros(3, 6))
    with pytest.raises(ShapeError, match=r"\(N, 6\).*'ur5'.*\(3, 7\)"):
        robot(torch.zeros(3, 7, dtype=F64))
    with pytest.raises(ShapeError):
        torchcal.robot.DHGeometry(
            a=[0.0], alpha=[0.0], d=[0.0], theta=[0.0], convention="standard", dtype=torch.float32
        )


def test_batched_and_looped_fk_agree():
    robot = torchcal.load_robot("ur10")
    q = random_q(robot, 12, seed=9).reshape(3, 4, 6)
    with torch.no_grad():
        T = robot(q)
        loop = torch.stack([robot(qi) for qi in q.reshape(-1, 6)]).reshape(3, 4, 4, 4)
    assert T.shape == (3, 4, 4, 4)
    assert (T - loop).abs().max().item() < 1e-14


def test_spec_errors(tmp_path):
    with pytest.raises(RobotSpecError, match="built-ins: .*ur10.*ur5"):
        torchcal.load_robot("ur99")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nconvention: standard\njoints:\n  - {a: 0.0, alpha: 0.0, theta: 0.0}\n")
    with pytest.raises(RobotSpecError, match="bad.yaml: joint 1: missing 'd'"):
        torchcal.load_robot(bad)
    bad.write_text("name: x\nconvention: sideways\njoints:\n  - {a: 0.0, alpha: 0.0, d: 0, theta: 0.0}\n")
    with pytest.raises(RobotSpecError, match="convention 'sideways'"):
        torchcal.load_robot(bad)
    bad.write_text("name: x\njoints:\n  - {a: zero, alpha: 0.0, d: 0, theta: 0.0}\n")
    with pytest.raises(RobotSpecError, match="'a' must be a number"):
        torchcal.load_robot(bad)
    urdf = tmp_path / "broken.urdf"
    urdf.write_text("<robot name='x'><link name='a'/>")
    with pytest.raises(RobotSpecError, match="broken.urdf"):
        torchcal.load_robot(urdf)
    with pytest.raises(RobotSpecError, match="tip link 'nope' not found"):
        torchcal.load_robot("ur5.urdf", tip_link="nope")


def test_urdf_tip_choice_and_ambiguity(tmp_path):
    two_tips = tmp_path / "y.urdf"
    two_tips.write_text(
        "<robot name='y'><link name='b'/><link name='l1'/><link name='l2'/>"
        "<joint name='j1' type='revolute'><parent link='b'/><child link='l1'/><axis xyz='0 0 1'/>"
        "<limit lower='-1' upper='1' effort='1' velocity='1'/></joint>"
        "<joint name='j2' type='revolute'><parent link='b'/><child link='l2'/><axis xyz='0 0 1'/>"
        "<limit lower='-1' upper='1' effort='1' velocity='1'/></joint></robot>"
    )
    with pytest.raises(RobotSpecError, match="--tip-link"):
        torchcal.load_robot(two_tips)
    robot = torchcal.load_robot(two_tips, tip_link="l2")
    assert robot.joint_names == ["j2"] and robot.dof == 1


def test_so3_exp_derivative_at_zero_is_the_generator():
    J = torch.autograd.functional.jacobian(tf.so3_exp, torch.zeros(3, dtype=F64))
    for k in range(3):
        e = torch.zeros(3, dtype=F64)
        e[k] = 1.0
        assert torch.allclose(J[..., k], tf.skew(e), atol=1e-15)


def test_rotation_round_trips():
    g = torch.Generator().manual_seed(0)
    rv = torch.randn(100, 3, generator=g, dtype=F64)
    rv = rv / rv.norm(dim=-1, keepdim=True) * torch.rand(100, 1, generator=g, dtype=F64) * 3.0
    R = tf.so3_exp(rv)
    assert torch.allclose(tf.so3_log(R), rv, atol=1e-10)
    assert torch.allclose(tf.rpy_to_matrix(tf.matrix_to_rpy(R)), R, atol=1e-14)
    T = tf.se3_from_vector(torch.randn(5, 6, generator=g, dtype=F64))
    assert torch.allclose(tf.invert(T) @ T, torch.eye(4, dtype=F64).expand(5, 4, 4), atol=1e-14)


@pytest.mark.parametrize("spec", ["ur10", "panda.urdf"])
def test_geometric_probe_jacobian_equals_autograd(spec):
    robot = torchcal.load_robot(spec)
    _set_random(robot, seed=3)
    q = random_q(robot, 10, seed=11)
    with torch.no_grad():
        p, J = robot.probe_jacobian(q)
    ref = torch.func.vmap(torch.func.jacfwd(lambda qi: robot.probe_in_base(qi[None])[0]))(q)
    assert torch.allclose(p, robot.probe_in_base(q).detach(), atol=1e-15)
    assert (J - ref).abs().max() < 1e-13


def test_no_poses_give_empty_results_of_the_right_shapes():
    # the chain holds the poses in the last dimension and reshapes by their count: none must work too
    robot = torchcal.load_robot("ur10")
    q = torch.zeros(0, robot.dof, dtype=F64)
    assert robot.probe_in_base(q).shape == (0, 3)
    assert robot.probe_jacobian(q)[1].shape == (0, 3, robot.dof)
    assert robot.gravity_torques(q, payload=1.0).shape == (0, robot.dof)
    assert robot.tracker_jacobian(q, [("geometry", 0), ("instrument", 2), ("tool", 1)])[1].shape == (0, 3, 3)
    assert robot.joint_frames(q)[0].shape == (0, robot.dof, 4, 4)


def test_probe_pose_is_probe_in_base_and_probe_rotation_from_one_chain():
    robot = torchcal.load_robot("ur5")
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        robot.geometry.delta.copy_(torch.randn(robot.geometry.delta.shape, generator=g, dtype=torch.float64) * 1e-3)
    with pytest.raises(Exception, match="no probe orientation"):
        robot.probe_pose(torch.zeros(1, 6, dtype=torch.float64))
    robot.enable_orientation(tf.so3_exp(torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64)))
    q = torch.randn(20, 6, generator=g, dtype=torch.float64)
    p, R = robot.probe_pose(q)
    assert torch.equal(p, robot.probe_in_base(q)) and torch.equal(R, robot.probe_rotation(q))
