"""URDF export: the calibrated robot written as URDF reads back to the same float64 geometry."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch

import torchcal
from torchcal.errors import RobotSpecError
from torchcal.robot import transforms as tf
from torchcal.robot import write_urdf
from torchcal.robot.export import RPY_TOLERANCE, exact_rpy
from torchcal.robot.load import resolve_robot_spec

F64 = torch.float64
# DH tables, a URDF robot made here (so that the URDF path is tested even without built-in URDFs),
# and the built-in URDFs where present
ROBOTS = ["ur5", "ur10", "exported", "panda.urdf", "ur5.urdf", "ur10_track", "exported_track"]


def random_q(robot, n, seed=0):
    g = torch.Generator().manual_seed(seed)
    lo, hi = robot.limits[:, 0].clamp(min=-math.pi), robot.limits[:, 1].clamp(max=math.pi)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)


def perturb(robot, seed):
    """Random non-zero corrections in every group and a tracker pose far from the identity."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        robot.geometry.delta.normal_(0.0, 1e-3, generator=g)
        rot = tf.rpy_to_matrix(torch.tensor([0.3, -0.2, 2.0], dtype=F64))
        robot.instrument.nominal.copy_(tf.homogeneous(rot, torch.tensor([2.5, -1.0, 0.4], dtype=F64)))
        robot.instrument.delta.normal_(0.0, 1e-3, generator=g)
        robot.tool.nominal.copy_(torch.tensor([0.01, -0.02, 0.15], dtype=F64))
        robot.tool.delta.normal_(0.0, 1e-3, generator=g)
    return robot


def make_robot(name, tmp_path):
    if name in ("exported", "exported_track"):
        # ur5 (or the UR10 on its prismatic track) written as URDF and loaded back is a URDFGeometry robot with
        # masses
        source = "ur5" if name == "exported" else "ur10_track"
        path = write_urdf(perturb(torchcal.load_robot(source), 7), tmp_path / f"{source}_nominal.urdf")
        robot = torchcal.load_robot(path, tip_link="flange")
        assert robot.kind == "urdf" and robot.has_masses
        assert robot.joint_types == torchcal.load_robot(source).joint_types
    else:
        try:
            resolve_robot_spec(name)
        except RobotSpecError:
            pytest.skip(f"robots/{name} is not there (yet)")
        robot = torchcal.load_robot(name)
    return perturb(robot, 1)


def reload(robot, path, tip=None):
    return torchcal.load_robot(path, base_link=robot.link_names[0], tip_link=tip or robot.link_names[-1])


@pytest.mark.parametrize("name", ROBOTS)
def test_round_trip_through_torchcal_loader(name, tmp_path):
    robot = make_robot(name, tmp_path)
    path = write_urdf(robot, tmp_path / "calibrated.urdf")
    back = reload(robot, path)
    q = random_q(robot, 50)
    with torch.no_grad():
        err = (back(q) - robot(q)).abs().max().item()
        err_origins = (back.geometry.origins() - robot.geometry.origins()).abs().max().item()
    print(f"{name}: max |T_base_flange difference| = {err:.3g}, origins {err_origins:.3g}")
    assert err <= 1e-9  # rounding only: ~1e-15 expected
    assert err_origins <= 1e-14
    assert back.joint_names == robot.joint_names
    assert back.link_names == robot.link_names
    assert torch.equal(back.limits, robot.limits)
    assert torch.equal(back.geometry.axes, robot.geometry.axes)
    assert back.has_masses == robot.has_masses
    assert torch.equal(back.masses, robot.masses)
    # the loader recomputes each com as (m c) / m: equal to the last bit or one ulp off
    torch.testing.assert_close(back.coms, robot.coms, rtol=0.0, atol=1e-15)


@pytest.mark.parametrize("name", ROBOTS)
def test_probe_and_tracker_frames(name, tmp_path):
    import yourdfpy

    robot = make_robot(name, tmp_path)
    path = write_urdf(robot, tmp_path / "calibrated.urdf")
    # the probe is the deepest leaf, which load_robot picks by itself
    with_probe = torchcal.load_robot(path)
    assert with_probe.link_names[-1] == "probe"
    q = random_q(robot, 50, seed=3)
    with torch.no_grad():
        expected = robot(q) @ tf.translation(robot.t_flange_probe())
        assert (with_probe(q) - expected).abs().max().item() <= 1e-9
        T_tracker_base = robot.T_tracker_base()
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False)
    T_base_tracker = torch.as_tensor(urdf.joint_map["tracker_joint"].origin, dtype=F64)
    assert urdf.joint_map["tracker_joint"].parent == robot.link_names[0]
    assert (tf.invert(T_base_tracker) - T_tracker_base).abs().max().item() <= 1e-14


def test_gimbal_locked_tracker_round_trips(tmp_path):
    import yourdfpy

    robot = perturb(torchcal.load_robot("ur5"), 2)
    # T_base_tracker with pitch exactly +pi/2: R[2, 0] = -1, R[0, 0] = R[1, 0] = R[2, 1] = R[2, 2] = 0
    c, s = math.cos(0.4), math.sin(0.4)
    R_base_tracker = torch.tensor([[0.0, -s, c], [0.0, c, s], [-1.0, 0.0, 0.0]], dtype=F64)
    with torch.no_grad():
        robot.instrument.set_matrix(tf.homogeneous(R_base_tracker.T, torch.tensor([1.0, 2.0, 0.5], dtype=F64)))
    urdf = yourdfpy.URDF.load(str(write_urdf(robot, tmp_path / "locked.urdf")), load_meshes=False)
    T_base_tracker = torch.as_tensor(urdf.joint_map["tracker_joint"].origin, dtype=F64)
    with torch.no_grad():
        assert (tf.invert(T_base_tracker) - robot.T_tracker_base()).abs().max().item() <= 1e-15


def test_exact_rpy_at_and_near_gimbal_lock():
    g = torch.Generator().manual_seed(0)
    needed_fallback = False
    for sign in (1.0, -1.0):
        for cp in [0.0, 1e-300, 1e-17, 1e-13, 1e-9, 1e-5, 1e-2]:
            roll, yaw = (torch.rand(2, generator=g, dtype=F64) * 2 - 1) * math.pi
            R = tf.rpy_to_matrix(torch.stack([roll, torch.tensor(sign * math.atan2(1.0, cp), dtype=F64), yaw]))
            if cp == 0.0:  # exactly locked, not just cos(pi/2) = 6e-17
                R[0, 0] = R[1, 0] = R[2, 1] = R[2, 2] = 0.0
                R[2, 0] = -sign
            err = (tf.rpy_to_matrix(torch.tensor(exact_rpy(R), dtype=F64)) - R).abs().max().item()
            assert err <= RPY_TOLERANCE, (sign, cp, err)
            plain = (tf.rpy_to_matrix(tf.matrix_to_rpy(R)) - R).abs().max().item()
            needed_fallback |= plain > RPY_TOLERANCE
    # the cases above include ones where matrix_to_rpy alone loses digits (it zeroes roll when cp < 1e-12)
    assert needed_fallback
    for _ in range(200):
        R = tf.rpy_to_matrix((torch.rand(3, generator=g, dtype=F64) * 2 - 1) * torch.tensor([math.pi, 1.5, math.pi]))
        err = (tf.rpy_to_matrix(torch.tensor(exact_rpy(R), dtype=F64)) - R).abs().max().item()
        assert err <= RPY_TOLERANCE


@pytest.mark.parametrize("name", ["ur5", "exported"])
def test_yourdfpy_validates(name, tmp_path):
    import yourdfpy

    path = write_urdf(make_robot(name, tmp_path), tmp_path / "calibrated.urdf")
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False)
    assert urdf.validate()


@pytest.mark.parametrize("name", ROBOTS)
def test_pytorch_kinematics_parser_agrees(name, tmp_path):
    pk = pytest.importorskip("pytorch_kinematics")
    robot = make_robot(name, tmp_path)
    path = write_urdf(robot, tmp_path / "calibrated.urdf")
    chain = pk.build_serial_chain_from_urdf(path.read_bytes(), robot.link_names[-1], robot.link_names[0])
    assert chain.get_joint_parameter_names() == robot.joint_names
    q = random_q(robot, 50, seed=5)
    T_pk = chain.forward_kinematics(q.float()).get_matrix().double()
    with torch.no_grad():
        T = robot(q)
    err = (T_pk - T).abs().max().item()
    print(f"{name}: pytorch-kinematics parser vs torchcal, max |T difference| = {err:.3g}")
    # pk's URDF parser turns rpy into float32 quaternions and computes FK in float32, so only ~1e-7
    # relative precision survives; torchcal's own loader (yourdfpy, float64) is the exact route.
    assert err <= 1e-6


def test_output_is_deterministic_and_atomic(tmp_path):
    robot = perturb(torchcal.load_robot("ur5"), 4)
    a = write_urdf(robot, tmp_path / "a.urdf").read_bytes()
    b = write_urdf(robot, tmp_path / "a.urdf").read_bytes()
    assert a == b
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.urdf"]  # no temporary file left behind
    text = a.decode()
    assert "generated by torchcal" in text.lower() and "T_base_tracker = inv(T_tracker_base)" in text
    assert '<robot name="ur5">' in text
    assert '<robot name="ur5_cal">' in write_urdf(robot, tmp_path / "b.urdf", name="ur5_cal").read_text()


def test_options_and_errors(tmp_path):
    robot = perturb(torchcal.load_robot("ur5"), 5)
    path = write_urdf(robot, tmp_path / "bare.urdf", probe=False, tracker=False)
    text = path.read_text()
    assert "probe" not in text.split("-->")[1] and "tracker" not in text.split("-->")[1]
    back = torchcal.load_robot(path)  # the flange is now the only leaf
    q = random_q(robot, 10)
    with torch.no_grad():
        assert np.abs((back(q) - robot(q)).numpy()).max() <= 1e-9
    with pytest.raises(RobotSpecError, match="does not exist"):
        write_urdf(robot, tmp_path / "missing" / "x.urdf")
    robot.link_names[3] = "probe"
    with pytest.raises(RobotSpecError, match="probe=False"):
        write_urdf(robot, tmp_path / "clash.urdf")


def test_tip_on_the_last_moving_link(tmp_path):
    # a URDF chain may end on the last joint's child: then O_tip = I and no tip joint is added
    nominal = write_urdf(torchcal.load_robot("ur5"), tmp_path / "ur5.urdf", probe=False, tracker=False)
    robot = perturb(torchcal.load_robot(nominal, tip_link="link6"), 6)
    assert robot.link_names[-2:] == ["link6", "link6"]
    path = write_urdf(robot, tmp_path / "calibrated.urdf")
    assert "link6_joint" not in path.read_text()
    back = reload(robot, path)
    q = random_q(robot, 20)
    with torch.no_grad():
        assert (back(q) - robot(q)).abs().max().item() <= 1e-9
        # the user's own file keeps its flange leaf beside the added probe: name the tip
        probe = torchcal.load_robot(path, tip_link="probe")
        assert (probe(q) - robot(q) @ tf.translation(robot.t_flange_probe())).abs().max() <= 1e-9


# ------------------------------------------------------------------ the user's own URDF, written back
KINOVA_LIKE = Path(__file__).parent / "data" / "kinova_like.urdf"


def _canonical(path, skip_joints=(), skip_frames=("probe", "tracker")):
    """The URDF's XML as nested tuples, without comments, the origins of ``skip_joints`` and the added frames."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()

    def node(el):
        kids = [c for c in el if isinstance(c.tag, str)]
        if el.tag == "joint" and el.get("name") in skip_joints:
            kids = [c for c in kids if c.tag != "origin"]
        return (el.tag, tuple(sorted(el.attrib.items())), (el.text or "").strip(), tuple(node(c) for c in kids))

    kids = [
        c
        for c in root
        if isinstance(c.tag, str)
        and not (c.tag == "link" and c.get("name") in skip_frames)
        and not (c.tag == "joint" and c.get("name") in {f"{f}_joint" for f in skip_frames})
    ]
    return root.tag, tuple(sorted(root.attrib.items())), tuple(node(c) for c in kids)


@pytest.mark.parametrize("source", ["panda.urdf", "ur5.urdf", "kinova"])
def test_user_urdf_kept_apart_from_the_origins(source, tmp_path):
    import yourdfpy

    path_in = KINOVA_LIKE if source == "kinova" else resolve_robot_spec(source)
    robot = perturb(torchcal.load_robot(path_in), 11)
    out = write_urdf(robot, tmp_path / "calibrated.urdf")
    # equal as XML apart from the chain's joint origins and the two added frames
    assert _canonical(out, robot.joint_names) == _canonical(path_in, robot.joint_names)
    # and the origins did change (the calibration is in the file)
    assert _canonical(out) != _canonical(path_in)
    a = yourdfpy.URDF.load(str(path_in), load_meshes=False, build_scene_graph=False)
    b = yourdfpy.URDF.load(str(out), load_meshes=False, build_scene_graph=False)
    assert [lk.name for lk in b.robot.links] == [lk.name for lk in a.robot.links] + ["probe", "tracker"]
    assert [j.name for j in b.robot.joints] == [j.name for j in a.robot.joints] + ["probe_joint", "tracker_joint"]
    for ja in a.robot.joints:
        jb = b.joint_map[ja.name]
        assert (jb.type, jb.parent, jb.child) == (ja.type, ja.parent, ja.child)
        assert np.array_equal(np.asarray(jb.axis), np.asarray(ja.axis))
        assert (ja.limit is None) == (jb.limit is None)
        if ja.limit is not None:
            assert (jb.limit.effort, jb.limit.velocity, jb.limit.lower, jb.limit.upper) == (
                ja.limit.effort,
                ja.limit.velocity,
                ja.limit.lower,
                ja.limit.upper,
            )
        if ja.name not in robot.joint_names:  # fixed joints keep their origin exactly
            assert np.array_equal(jb.origin, ja.origin)
    for la in a.robot.links:
        lb = b.link_map[la.name]
        assert (la.inertial is None) == (lb.inertial is None)
        if la.inertial is not None:
            assert la.inertial.mass == lb.inertial.mass
            assert np.array_equal(la.inertial.inertia, lb.inertial.inertia)
        assert [v.geometry.mesh.filename for v in la.visuals if v.geometry.mesh] == [
            v.geometry.mesh.filename for v in lb.visuals if v.geometry.mesh
        ]
    # FK through the file equals the calibrated model's
    back = torchcal.load_robot(out, tip_link=robot.tip_link)
    q = random_q(robot, 30, seed=2)
    with torch.no_grad():
        assert (back(q) - robot(q)).abs().max().item() <= 1e-12
        assert (
            torchcal.load_robot(out, tip_link="probe")(q) - robot(q) @ tf.translation(robot.t_flange_probe())
        ).abs().max().item() <= 1e-12


def test_kinova_like_details_survive(tmp_path):
    robot = perturb(torchcal.load_robot(KINOVA_LIKE), 12)
    text = write_urdf(robot, tmp_path / "k.urdf").read_text()
    for kept in (
        'type="continuous"',
        'effort="39" velocity="1.3963"',
        "package://kortex_description",
        'name="EndEffector" type="fixed"',
        '<link name="Shoulder Link">',
        "<transmission",
        "<gazebo reference",
        "safety_controller",
        'xmlns:xacro="http://www.ros.org/wiki/xacro"',
        "values invented",
    ):
        assert kept in text, kept
    assert "EndEffector_Link_joint" not in text
    assert "1e-06" not in text  # no placeholder inertia


def test_user_urdf_notes_and_reexport(tmp_path):
    robot = perturb(torchcal.load_robot("ur5.urdf"), 13)
    first = write_urdf(robot, tmp_path / "a.urdf", notes=["NOT in this URDF: compliance(joint 2)."])
    assert "NOT in this URDF: compliance(joint 2)." in first.read_text().split("-->")[0]
    # calibrating an exported file again updates its probe/tracker frames instead of adding twins
    again = perturb(torchcal.load_robot(first, tip_link="tool0"), 14)
    second = write_urdf(again, tmp_path / "b.urdf")
    assert second.read_text().count('<link name="probe"/>') == 1
    q = random_q(again, 10)
    with torch.no_grad():
        assert (
            torchcal.load_robot(second, tip_link="probe")(q) - again(q) @ tf.translation(again.t_flange_probe())
        ).abs().max().item() <= 1e-12
