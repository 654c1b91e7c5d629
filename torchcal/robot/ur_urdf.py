"""UR5 / UR10 URDFs generated from the standard DH tables in ``robots/urX.yaml`` (``scripts/make_ur_urdf.py``).

Independent of the rest of torchcal on purpose (numpy, PyYAML and the standard library; only the error class is
torchcal's), so the URDFs can be regenerated and audited without the package's model code.

The chain follows ``urdf/ur_macro.xacro`` of Universal_Robots_ROS2_Description (BSD-3-Clause) with
its *default* (uncalibrated) kinematics, which is an exact rewrite of UR's standard DH table::

    base_link -[fixed, rpy 0 0 pi]-> base_link_inertia      (= DH frame 0, the controller's base)
      -[shoulder_pan_joint,  xyz 0 0 d1]-> shoulder_link
      -[shoulder_lift_joint, rpy pi/2 0 0]-> upper_arm_link
      -[elbow_joint,         xyz a2 0 0]-> forearm_link
      -[wrist_1_joint,       xyz a3 0 d4]-> wrist_1_link
      -[wrist_2_joint,       xyz 0 -d5 0, rpy pi/2 0 0]-> wrist_2_link
      -[wrist_3_joint,       xyz 0 d6 0,  rpy pi/2 pi pi]-> wrist_3_link
      -[fixed, rpy 0 -pi/2 -pi/2]-> flange -[fixed, rpy pi/2 0 pi/2]-> tool0   (= DH frame 6)
    base_link -[fixed, rpy 0 0 pi]-> base                   (= DH frame 0)

so that T(base_link -> tool0) = Rz(pi) @ T_DH(q) and T(base -> tool0) = T_DH(q). The xacro's default
kinematics files write pi/2 as 1.570796327 and carry ~1e-11 m z-offsets in wrist_2/wrist_3 (DH
round-off); here they are exactly pi/2 and 0.

Inertials: mass and centre of mass from the YAML (the YAML gives the centre of mass in DH frame i; it
is moved into the URDF link frame with the fixed transform between the two, computed from both
forward kinematics at q = 0). The inertia tensors are APPROXIMATE: a solid cylinder per link whose
length and radius are derived from the DH lengths (see ``cylinder``); no meshes, no visual or
collision elements.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import yaml

from torchcal.errors import RobotSpecError

MODELS = ("ur5", "ur10")
PI = math.pi
HALF_PI = math.pi / 2

#: UR's joint names, base to tip (the URDF's and the controller's)
JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
LINK_NAMES = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")

# Effort [Nm] and velocity [rad/s] limits per joint, as in Universal_Robots_ROS2_Description
# config/urX/joint_limits.yaml (from UR's user manuals and "Max. joint torques" article).
DRIVE_LIMITS = {
    "ur5": {"effort": (150.0, 150.0, 150.0, 28.0, 28.0, 28.0), "velocity": (PI,) * 6},
    "ur10": {
        "effort": (330.0, 330.0, 150.0, 56.0, 56.0, 56.0),
        "velocity": (math.radians(120.0), math.radians(120.0), PI, PI, PI, PI),
    },
}

TITLES = {"ur5": "Universal Robots UR5 (CB3)", "ur10": "Universal Robots UR10 (CB3)"}

# UR's standard DH pattern that the xacro structure encodes (alpha per joint; theta = 0)
UR_ALPHA = (HALF_PI, 0.0, 0.0, HALF_PI, -HALF_PI, 0.0)


# ---------------------------------------------------------------------------------------- geometry
def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def homogeneous(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def urdf_origin(xyz, rpy) -> np.ndarray:
    """URDF <origin>: translation xyz, then fixed-axis roll-pitch-yaw, R = Rz(y) Ry(p) Rx(r)."""
    r, p, y = rpy
    return homogeneous(rot_z(y) @ rot_y(p) @ rot_x(r), xyz)


def dh_standard(a: float, alpha: float, d: float, theta: float) -> np.ndarray:
    """Standard DH link transform T = Rz(theta) Tz(d) Tx(a) Rx(alpha)."""
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array(
        [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]
    )


def dh_frames(table: list[dict], q) -> list[np.ndarray]:
    """DH frames 0..n in frame 0 (frame 0 included)."""
    out = [np.eye(4)]
    for row, qi in zip(table, q):
        out.append(out[-1] @ dh_standard(row["a"], row["alpha"], row["d"], qi + row["theta"]))
    return out


# ---------------------------------------------------------------------------------------- model
def load_table(path: Path) -> dict:
    """The DH rows, joint limits, masses and centres of mass of a UR YAML; refuses a table off UR's DH pattern."""
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    if str(doc.get("convention", "standard")).lower() != "standard":
        raise RobotSpecError(f"{path}: expected a standard DH table")
    joints = doc["joints"]
    if len(joints) != 6:
        raise RobotSpecError(f"{path}: expected 6 joints, got {len(joints)}")
    rows = []
    for i, j in enumerate(joints):
        row = {k: float(j[k]) for k in ("a", "alpha", "d", "theta", "lower", "upper", "mass")}
        row["com"] = [float(c) for c in j["com"]]
        rows.append(row)
        # the URDF structure below is only exact for UR's DH pattern: check it holds
        ok = row["alpha"] == UR_ALPHA[i] and row["theta"] == 0.0
        ok &= row["a"] == 0.0 if i in (0, 3, 4, 5) else row["d"] == 0.0
        if not ok:
            raise RobotSpecError(
                f"{path}: joint {i + 1} does not follow UR's DH pattern "
                f"(alpha {UR_ALPHA}, theta 0, a1=a4=a5=a6=0, d2=d3=0)"
            )
    return {"name": str(doc.get("name", path.stem)), "path": path, "joints": rows}


def chain_joints(model: dict) -> list[dict]:
    """Joints of the URDF in file order; each has name, type, parent, child, xyz, rpy (+ index for revolute)."""
    j = model["joints"]
    d1, a2, a3, d4, d5, d6 = j[0]["d"], j[1]["a"], j[2]["a"], j[3]["d"], j[4]["d"], j[5]["d"]
    zero = (0.0, 0.0, 0.0)

    def fixed(name, parent, child, xyz, rpy):
        return {"name": name, "type": "fixed", "parent": parent, "child": child, "xyz": xyz, "rpy": rpy}

    def revolute(i, parent, xyz, rpy):
        return {
            "name": JOINT_NAMES[i],
            "type": "revolute",
            "parent": parent,
            "child": LINK_NAMES[i],
            "xyz": xyz,
            "rpy": rpy,
            "index": i,
        }

    return [
        fixed("base_link-base_link_inertia", "base_link", "base_link_inertia", zero, (0.0, 0.0, PI)),
        revolute(0, "base_link_inertia", (0.0, 0.0, d1), zero),
        revolute(1, LINK_NAMES[0], zero, (HALF_PI, 0.0, 0.0)),
        revolute(2, LINK_NAMES[1], (a2, 0.0, 0.0), zero),
        revolute(3, LINK_NAMES[2], (a3, 0.0, d4), zero),
        revolute(4, LINK_NAMES[3], (0.0, -d5, 0.0), (HALF_PI, 0.0, 0.0)),
        revolute(5, LINK_NAMES[4], (0.0, d6, 0.0), (HALF_PI, PI, PI)),
        fixed("wrist_3-flange", LINK_NAMES[5], "flange", zero, (0.0, -HALF_PI, -HALF_PI)),
        fixed("flange-tool0", "flange", "tool0", zero, (HALF_PI, 0.0, HALF_PI)),
        fixed("base_link-base_fixed_joint", "base_link", "base", zero, (0.0, 0.0, PI)),
    ]


def link_poses(joints: list[dict], q, root: str = "base_link") -> dict[str, np.ndarray]:
    """Pose in ``root`` of every link below it, for joint angles q (revolute joints about their z axis)."""
    poses = {root: np.eye(4)}
    pending = list(joints)
    progress = True
    while progress:
        progress = False
        for jt in list(pending):
            if jt["parent"] in poses:
                T = poses[jt["parent"]] @ urdf_origin(jt["xyz"], jt["rpy"])
                if jt["type"] == "revolute":
                    T = T @ homogeneous(rot_z(q[jt["index"]]))
                poses[jt["child"]] = T
                pending.remove(jt)
                progress = True
    return poses


def cylinder(model: dict, i: int) -> tuple[int, float, float]:
    """Approximate solid cylinder (axis index in the link frame, length, radius) for moving link i.

    A rough geometric stand-in only: lengths from the DH table, radii 0.6 d5 (shoulder, upper
    arm) and 0.45 d5 (forearm, wrists), to 0.1 mm; 0.0568 m / 0.0426 m on a UR5.
    """
    j = model["joints"]
    d5 = j[4]["d"]
    big, small = round(0.6 * d5, 4), round(0.45 * d5, 4)
    return [
        (2, j[0]["d"], big),  # shoulder_link: along the pan axis (z)
        (0, abs(j[1]["a"]), big),  # upper_arm_link: along x, towards the elbow
        (0, abs(j[2]["a"]), small),  # forearm_link: along x, towards wrist 1
        (2, j[4]["d"], small),  # wrist_1_link: along z
        (2, j[5]["d"], small),  # wrist_2_link: along z
        (2, 0.5 * j[5]["d"], small),  # wrist_3_link: short disc along z
    ][i]


def cylinder_inertia(mass: float, axis: int, length: float, radius: float) -> np.ndarray:
    """Principal moments [ixx, iyy, izz] of a solid cylinder about its centre, its axis along ``axis``."""
    along = 0.5 * mass * radius**2
    across = mass * (3.0 * radius**2 + length**2) / 12.0
    moments = np.full(3, across)
    moments[axis] = along
    return moments


def inertials(model: dict) -> list[dict]:
    """Per moving link: mass, centre of mass in the URDF link frame, diagonal inertia."""
    q0 = np.zeros(6)
    links = link_poses(chain_joints(model), q0, root="base_link_inertia")  # base_link_inertia = DH frame 0
    frames = dh_frames(model["joints"], q0)
    out = []
    for i, row in enumerate(model["joints"]):
        X = np.linalg.inv(links[LINK_NAMES[i]]) @ frames[i + 1]  # DH frame i in URDF link i (constant in q)
        R = np.round(X[:3, :3])  # a signed permutation for this structure: make it exact
        if np.abs(R - X[:3, :3]).max() > 1e-12:
            raise RobotSpecError(f"{model['path']}: link {LINK_NAMES[i]} is not axis-aligned with DH frame {i + 1}")
        # rounded to 1e-12 m: drops floating-point noise such as -0.24225000000000005
        com = [round(float(c), 12) for c in R @ np.asarray(row["com"]) + X[:3, 3]]
        axis, length, radius = cylinder(model, i)
        out.append(
            {
                "mass": row["mass"],
                "com": com,
                "inertia": cylinder_inertia(row["mass"], axis, length, radius),
                "cylinder": (("x", "y", "z")[axis], length, radius),
            }
        )
    return out


# ---------------------------------------------------------------------------------------- output
def num(x: float) -> str:
    """A float as Python writes it (shortest string that round-trips, up to 17 significant digits)."""
    x = float(x)
    return repr(0.0 if x == 0.0 else x)


def nums(xs) -> str:
    return " ".join(num(x) for x in xs)


def render(model: dict, source: str) -> str:
    """The URDF text of ``model`` (:func:`load_table`); ``source`` names the YAML in the header comment."""
    name = model["name"]
    lim = DRIVE_LIMITS[name]
    inert = inertials(model)
    out = [
        '<?xml version="1.0"?>',
        "<!--",
        f"  {TITLES.get(name, name)}: kinematic chain with approximate inertials, no meshes.",
        "",
        f"  Generated by scripts/make_ur_urdf.py from {source}; do not edit by hand, edit the YAML",
        "  and rerun the script (its check mode verifies that this file is up to date).",
        "",
        "  Nominal values from Universal Robots' published DH table (\"DH parameters for",
        '  calculations of kinematics and dynamics", universal-robots.com): link lengths, masses and',
        "  centres of mass (moved from DH frame i into the URDF link frames). Effort and velocity limits",
        "  as in Universal_Robots_ROS2_Description config/" + name + "/joint_limits.yaml; position limits",
        "  from the YAML.",
        "",
        "  Structure (link and joint names, frame conventions) after Universal_Robots_ROS2_Description,",
        "  urdf/ur_macro.xacro with its default (uncalibrated) kinematics, BSD-3-Clause licence;",
        "  meshes, visual, collision, ros2_control and transmission elements are not included.",
        "  The chain is an exact rewrite of the DH table: T(base_link, tool0) = Rz(pi) T_DH(q) and",
        "  T(base, tool0) = T_DH(q), DH frame 0 to frame 6.",
        "",
        "  The inertia tensors are APPROXIMATE (solid cylinders sized from the DH lengths), diagonal",
        "  in the link frame; only the masses and centres of mass come from the published table.",
        "-->",
        f'<robot name="{name}">',
        '  <link name="base_link"/>',
        '  <link name="base_link_inertia"/>',
    ]
    for i, link in enumerate(LINK_NAMES):
        m = inert[i]
        ax, length, radius = m["cylinder"]
        ixx, iyy, izz = m["inertia"]
        out += [
            f'  <link name="{link}">',
            f"    <!-- inertia: solid cylinder along {ax}, length {num(length)} m, radius {num(radius)} m"
            " (approximate) -->",
            "    <inertial>",
            f'      <origin xyz="{nums(m["com"])}" rpy="0.0 0.0 0.0"/>',
            f'      <mass value="{num(m["mass"])}"/>',
            f'      <inertia ixx="{num(ixx)}" ixy="0.0" ixz="0.0" iyy="{num(iyy)}" iyz="0.0" izz="{num(izz)}"/>',
            "    </inertial>",
            "  </link>",
        ]
    out += ['  <link name="flange"/>', '  <link name="tool0"/>', '  <link name="base"/>']
    for jt in chain_joints(model):
        out.append(f'  <joint name="{jt["name"]}" type="{jt["type"]}">')
        out.append(f'    <parent link="{jt["parent"]}"/>')
        out.append(f'    <child link="{jt["child"]}"/>')
        out.append(f'    <origin xyz="{nums(jt["xyz"])}" rpy="{nums(jt["rpy"])}"/>')
        if jt["type"] == "revolute":
            i = jt["index"]
            row = model["joints"][i]
            out.append('    <axis xyz="0 0 1"/>')
            out.append(
                f'    <limit lower="{num(row["lower"])}" upper="{num(row["upper"])}" '
                f'effort="{num(lim["effort"][i])}" velocity="{num(lim["velocity"][i])}"/>'
            )
            out.append('    <dynamics damping="0.0" friction="0.0"/>')
        out.append("  </joint>")
    out.append("</robot>")
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------- checks
#: float64 everywhere except pytorch_kinematics' URDF reader, which parses rpy as float32
TOLERANCE = {"pytorch_kinematics": 1e-6}


def parse_urdf(text: str) -> list[dict]:
    """Joints of a URDF text (stdlib XML; independent of the generator's joint list)."""
    root = ET.fromstring(text)
    joints = []
    for el in root.iter("joint"):
        o = el.find("origin")
        xyz = [float(v) for v in o.get("xyz", "0 0 0").split()] if o is not None else [0.0] * 3
        rpy = [float(v) for v in o.get("rpy", "0 0 0").split()] if o is not None else [0.0] * 3
        jt = {
            "name": el.get("name"),
            "type": el.get("type"),
            "parent": el.find("parent").get("link"),
            "child": el.find("child").get("link"),
            "xyz": xyz,
            "rpy": rpy,
        }
        if jt["type"] == "revolute":
            axis = [float(v) for v in el.find("axis").get("xyz").split()]
            if axis != [0.0, 0.0, 1.0]:
                raise ValueError(f"joint {jt['name']}: axis {axis}, expected 0 0 1")
            jt["index"] = JOINT_NAMES.index(jt["name"])
        joints.append(jt)
    return joints


def check_numerics(model: dict, text: str, path: Path, n: int = 20, seed: int = 0) -> dict[str, float]:
    """Max |URDF FK - DH FK| over n random q (and the same through yourdfpy/pytorch_kinematics if present).

    Keys: ``urdf`` (this file's own XML parser, base_link -> tool0 vs Rz(pi) T_DH), ``base`` (base -> tool0
    vs T_DH), ``com`` (centres of mass in space), ``yourdfpy``, ``pytorch_kinematics``. The last is only
    good to ~1e-7: pytorch_kinematics' URDF reader converts every rpy to float32. A key is missing where its
    library is not installed.
    """
    joints = parse_urdf(text)
    rng = np.random.default_rng(seed)
    lo = np.array([r["lower"] for r in model["joints"]])
    hi = np.array([r["upper"] for r in model["joints"]])
    qs = lo + (hi - lo) * rng.random((n, 6))
    Rz_pi = homogeneous(rot_z(PI))
    root = ET.fromstring(text)
    com_urdf = {
        lk.get("name"): np.array([float(v) for v in lk.find("inertial/origin").get("xyz").split()])
        for lk in root.iter("link")
        if lk.find("inertial") is not None
    }
    worst = {"urdf": 0.0, "base": 0.0, "com": 0.0}
    refs = []
    for q in qs:
        poses = link_poses(joints, q)
        frames = dh_frames(model["joints"], q)
        ref = Rz_pi @ frames[-1]
        refs.append(ref)
        worst["urdf"] = max(worst["urdf"], np.abs(poses["tool0"] - ref).max())
        worst["base"] = max(worst["base"], np.abs(np.linalg.inv(poses["base"]) @ poses["tool0"] - frames[-1]).max())
        for i, link in enumerate(LINK_NAMES):  # the centre of mass lands on the same point in space
            c_dh = (Rz_pi @ frames[i + 1] @ np.append(model["joints"][i]["com"], 1.0))[:3]
            c_urdf = (poses[link] @ np.append(com_urdf[link], 1.0))[:3]
            worst["com"] = max(worst["com"], np.abs(c_dh - c_urdf).max())
    refs = np.stack(refs)
    try:
        import yourdfpy
    except ImportError:  # optional: the check runs without it
        pass
    else:
        u = yourdfpy.URDF.load(str(path), load_meshes=False, build_scene_graph=True)
        err = 0.0
        for q, ref in zip(qs, refs):
            u.update_cfg(dict(zip(JOINT_NAMES, q)))
            err = max(err, np.abs(u.get_transform("tool0", "base_link") - ref).max())
        worst["yourdfpy"] = err
    try:
        import pytorch_kinematics as pk
        import torch
    except ImportError:  # optional: the check runs without it
        pass
    else:
        chain = pk.build_serial_chain_from_urdf(path.read_bytes(), "tool0", "base_link").to(dtype=torch.float64)
        order = [JOINT_NAMES.index(nm) for nm in chain.get_joint_parameter_names()]
        T = chain.forward_kinematics(torch.tensor(qs[:, order], dtype=torch.float64)).get_matrix().numpy()
        worst["pytorch_kinematics"] = float(np.abs(T - refs).max())
    return {k: float(v) for k, v in worst.items()}
