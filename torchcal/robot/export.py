"""Write a robot's current (calibrated) geometry as a URDF that reads back to the same float64 numbers.

Two routes:

* A robot loaded from a URDF (``robot.kind == "urdf"`` and its source file still there): the user's own
  description is written back with only the origins of the chain's movable joints changed to their
  calibrated values (:func:`user_urdf_string`); meshes, inertias, limits, joint types, names, materials,
  transmissions, plugins and comments survive as they were. Two fixed frames are added (or, where the file
  is a previous torchcal export that already has them, updated): ``probe`` and ``tracker`` as below.
* A DH robot: a URDF is generated (:func:`urdf_string`), as follows.

The generated file holds the chain exactly as torchcal computes it, ``T_base_flange(q) = O_1 R_1(q_1) ... O_n R_n(q_n)
O_tip``: one revolute or prismatic joint per robot joint with origin ``O_i``, the joint's axis and limits (rad or
m), a fixed joint to the tip with ``O_tip``, and optionally two extra fixed frames carrying the rest of the
calibration:

* ``probe``, fixed to the tip at the lever arm ``t_flange_probe`` (no rotation);
* ``tracker``, fixed to the base at ``T_base_tracker = inv(T_tracker_base)``.

Every number is written with ``repr(float)``, the shortest string that parses back to the same float64,
and every origin rotation is written as an ``rpy`` triple that reproduces the rotation matrix to 1e-15
(checked per origin; see :func:`exact_rpy`), so reloading with :func:`torchcal.robot.load_urdf` gives
the same forward kinematics to rounding (~1e-15 m).

Not calibrated, hence placeholders: joint ``effort`` and ``velocity`` limits (written as 0) and the link
inertia tensors (a tiny diagonal, :data:`PLACEHOLDER_INERTIA`); link masses and centres of mass are the
robot's own when it has them.
"""

from __future__ import annotations

import io
import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import torch

from torchcal.errors import RobotSpecError, ShapeError
from torchcal.robot import transforms as tf
from torchcal.robot.model import RobotModel
from torchcal.robot.readings import READINGS_MAP_TAG

#: Diagonal of the placeholder inertia tensor [kg m^2] written for each moving link: torchcal does not
#: model link inertias (only masses and centres of mass, for gravity torques); URDF consumers need one.
PLACEHOLDER_INERTIA = 1e-6

#: How closely the written ``rpy`` must reproduce each origin's rotation matrix (max abs element).
RPY_TOLERANCE = 1e-15

_IDENTITY_RPY = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ExportOptions:
    """What :func:`write_urdf` adds to the robot's chain and how it names it (both routes).

    Attributes:
        probe: add the ``probe`` link (the calibrated lever arm, fixed to the tip).
        tracker: add the ``tracker`` link (the instrument pose, fixed to the base).
        name: the URDF robot name (None: the robot's own).
        notes: extra lines for the header comment (what the URDF leaves out of the calibration).
    """

    probe: bool = True
    tracker: bool = True
    name: str | None = None
    notes: tuple[str, ...] = ()


def _calibrated(robot: RobotModel) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The calibrated numbers both routes write, float64 on the CPU: the joint origins ``O`` ``(dof + 1, 4, 4)``,
    ``T_base_tracker`` ``(4, 4)`` and ``t_flange_probe`` ``(3,)`` [m] (a robot calibrated from several stations or
    with several probes: the first station's tracker frame and the first probe's lever arm; report.json has all)."""
    with torch.no_grad():
        O = robot.geometry.origins().detach().to("cpu", torch.float64)
        T_base_tracker = tf.invert(robot.T_tracker_base().detach().to("cpu", torch.float64))
        t_flange_probe = robot.t_flange_probe().detach().to("cpu", torch.float64)
    return O, T_base_tracker, t_flange_probe


def _num(x) -> str:
    return repr(float(x))


def _vec(v) -> str:
    return " ".join(_num(x) for x in v)


def _rpy_error(R: torch.Tensor, rpy: torch.Tensor) -> float:
    return float((tf.rpy_to_matrix(rpy) - R).abs().max())


def _sequential_rpy(R: torch.Tensor) -> torch.Tensor:
    """Pitch and yaw from the first column, then roll from what is left: exact also at (near) gimbal lock.

    Near pitch = +-pi/2 the first column ``(cy cp, sy cp, -sp)`` fixes yaw only to ~eps / cp, but the
    roll computed from ``Ry(pitch)^T Rz(yaw)^T R`` absorbs that error, so the product reproduces ``R``
    to rounding (the yaw error only enters the elements of size ~cp, multiplied by cp).
    """
    cp = torch.hypot(R[0, 0], R[1, 0])
    pitch = torch.atan2(-R[2, 0], cp)
    yaw = torch.atan2(R[1, 0], R[0, 0])
    M = tf.rot_y(pitch).T @ tf.rot_z(yaw).T @ R  # = Rx(roll) up to rounding
    roll = torch.atan2(M[2, 1] - M[1, 2], M[1, 1] + M[2, 2])
    return torch.stack([roll, pitch, yaw])


def exact_rpy(R: torch.Tensor) -> tuple[float, float, float]:
    """URDF ``rpy`` of a rotation ``R (3, 3)`` such that ``rpy_to_matrix(rpy)`` reproduces ``R`` to 1e-15.

    Tries :func:`torchcal.robot.transforms.matrix_to_rpy` first; where it loses digits (near gimbal lock
    it zeroes the roll, an error of the order of cos(pitch)) it falls back to :func:`_sequential_rpy`.

    Raises:
        ShapeError: ``R`` is not a rotation matrix (no decomposition reproduces it to 1e-12).
    """
    R = R.detach().to(dtype=torch.float64, device="cpu")
    best, best_err = None, math.inf
    for decompose in (tf.matrix_to_rpy, _sequential_rpy):
        rpy = decompose(R)
        err = _rpy_error(R, rpy)
        if err < best_err:
            best, best_err = rpy, err
        if err <= RPY_TOLERANCE:
            break
    if best_err > 1e-12:
        raise ShapeError(
            f"expected a rotation matrix, got one that no roll-pitch-yaw reproduces better than "
            f"{best_err:.3g}: {R.tolist()}"
        )
    return tuple(float(a) for a in best)


def _origin(T: torch.Tensor) -> str:
    rpy = exact_rpy(T[:3, :3])
    return f'<origin xyz="{_vec(T[:3, 3])}" rpy="{_vec(rpy)}"/>'


def _comment(text: str) -> str:
    return text.replace("--", "- -")


def urdf_string(robot: RobotModel, options: ExportOptions | None = None) -> str:
    """The URDF text that :func:`write_urdf` writes for a DH robot (deterministic: no date, fixed formatting)."""
    opts = options or ExportOptions()
    probe, tracker = opts.probe, opts.tracker
    O, T_base_tracker, t_flange_probe = _calibrated(robot)
    with torch.no_grad():
        axes = robot.geometry.axes.detach().to("cpu", torch.float64)
        limits = robot.joint_limits.detach().to("cpu", torch.float64)
        A = robot.readings.matrix().detach().to("cpu", torch.float64)
        b = robot.readings.offset.detach().to("cpu", torch.float64)
        masses = robot.masses.detach().to("cpu", torch.float64)
        coms = robot.coms.detach().to("cpu", torch.float64)

    dof = robot.n_joints
    links, tip_is_last = _chain_links(robot, O, probe, tracker)
    base, tip, last = links[0], links[-1], links[-2]
    mimic = _mimic_rows(A, b) if robot.has_readings_map else {}
    out = ['<?xml version="1.0"?>', "<!--"]
    out += [f"  {_comment(line)}" for line in _urdf_header(robot, opts, A, b, mimic)]
    robot_name = robot.name if opts.name is None else opts.name
    out += ["-->", f"<robot name={quoteattr(robot_name)}>"]
    out += _link_xml(base)
    for i in range(dof):
        out += _link_xml(links[i + 1], _inertial_xml(coms[i], masses[i]) if robot.has_masses else None)
        extra = [
            f'<axis xyz="{_vec(axes[i])}"/>',
            f'<limit lower="{_num(limits[i, 0])}" upper="{_num(limits[i, 1])}" effort="0.0" velocity="0.0"/>',
        ]
        if i in mimic:
            extra.append(
                f"<mimic joint={quoteattr(robot.joint_names[mimic[i][0]])} "
                f'multiplier="{_num(mimic[i][1])}" offset="{_num(mimic[i][2])}"/>'
            )
        kind = robot.geometry.joint_types[i]
        out += _joint_xml(robot.joint_names[i], kind, links[i], links[i + 1], _origin(O[i]), extra)
    if not tip_is_last:
        out += _link_xml(tip) + _joint_xml(f"{tip}_joint", "fixed", last, tip, _origin(O[-1]), [])
    if probe:
        lever = f'<origin xyz="{_vec(t_flange_probe)}" rpy="{_vec(_IDENTITY_RPY)}"/>'
        out += _link_xml("probe") + _joint_xml("probe_joint", "fixed", tip, "probe", lever, [])
    if tracker:
        out += _link_xml("tracker") + _joint_xml("tracker_joint", "fixed", base, "tracker", _origin(T_base_tracker), [])
    out.append("</robot>")
    return "\n".join(out) + "\n"


def _chain_links(robot: RobotModel, O: torch.Tensor, probe: bool, tracker: bool) -> tuple[list[str], bool]:
    """The robot's link names (base, the link moved by each joint, tip) and whether the tip is the last moving link
    (no separate tip link to write); refused where the names do not fit the chain or would occur twice in the URDF."""
    dof = robot.n_joints
    links = list(robot.link_names)
    if len(links) != dof + 2:
        raise RobotSpecError(
            f"robot '{robot.name}' has {len(links)} link names, expected dof + 2 = {dof + 2} "
            "(base, the link moved by each joint, tip)"
        )
    tip, last = links[-1], links[-2]
    # a chain that ends on its last moving link has O_tip = I and no separate tip link to write
    tip_is_last = tip == last
    if tip_is_last and not torch.equal(O[-1], torch.eye(4, dtype=O.dtype)):
        raise RobotSpecError(
            f"robot '{robot.name}': tip link '{tip}' is the last moving link but O_tip is not the identity"
        )
    link_list = links[:-1] if tip_is_last else list(links)
    joint_list = list(robot.joint_names) + ([] if tip_is_last else [f"{tip}_joint"])
    if probe:
        link_list.append("probe")
        joint_list.append("probe_joint")
    if tracker:
        link_list.append("tracker")
        joint_list.append("tracker_joint")
    for kind, names in (("link", link_list), ("joint", joint_list)):
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise RobotSpecError(
                f"cannot write robot '{robot.name}' as URDF: {kind} names {dup} occur twice"
                + (
                    "; pass probe=False / tracker=False if the robot already has such frames"
                    if {"probe", "tracker", "probe_joint", "tracker_joint"} & set(dup)
                    else ""
                )
            )
    return links, tip_is_last


def _urdf_header(robot: RobotModel, opts: ExportOptions, A: torch.Tensor, b: torch.Tensor, mimic: dict) -> list[str]:
    """The header comment's lines: where the file comes from and which of its numbers are calibrated."""
    from torchcal._version import __version__

    base, tip = robot.link_names[0], robot.link_names[-1]
    source = robot.source or "constructed in memory"
    header = [
        f"Generated by torchcal {__version__} from robot '{robot.name}' ({robot.kind} geometry, source: {source}).",
        "Joint origins, axes and limits are the robot's current (calibrated) geometry; every number is",
        "written with repr() and reads back to the same float64.",
    ]
    if opts.tracker:
        header.append(
            f"Link 'tracker': the calibrated instrument pose, fixed to '{base}' at "
            "T_base_tracker = inv(T_tracker_base)."
        )
    if opts.probe:
        header.append(f"Link 'probe': the calibrated lever arm t_flange_probe, fixed to '{tip}' without rotation.")
    header.append("Joint effort/velocity limits (0) are placeholders, not calibrated.")
    if robot.has_masses:
        header.append(
            f"Link masses and centres of mass are the robot's; inertia tensors are a placeholder "
            f"diagonal ({PLACEHOLDER_INERTIA!r} kg m^2), not calibrated."
        )
    if robot.has_readings_map:
        header += _readings_note(robot, A, b, mimic)
    return header + list(opts.notes)


def _inertial_xml(com: torch.Tensor, mass: torch.Tensor) -> str:
    """A link's ``<inertial>``: its mass and centre of mass, with the placeholder inertia tensor."""
    return "\n".join(
        [
            "    <inertial>",
            f'      <origin xyz="{_vec(com)}" rpy="{_vec(_IDENTITY_RPY)}"/>',
            f'      <mass value="{_num(mass)}"/>',
            f'      <inertia ixx="{_num(PLACEHOLDER_INERTIA)}" ixy="0.0" ixz="0.0" '
            f'iyy="{_num(PLACEHOLDER_INERTIA)}" iyz="0.0" izz="{_num(PLACEHOLDER_INERTIA)}"/>',
            "    </inertial>",
        ]
    )


def _link_xml(name: str, inertial: str | None = None) -> list[str]:
    if inertial is None:
        return [f"  <link name={quoteattr(name)}/>"]
    return [f"  <link name={quoteattr(name)}>", inertial, "  </link>"]


def _joint_xml(name: str, kind: str, parent: str, child: str, origin: str, extra: list[str]) -> list[str]:
    return [
        f"  <joint name={quoteattr(name)} type={quoteattr(kind)}>",
        f"    <parent link={quoteattr(parent)}/>",
        f"    <child link={quoteattr(child)}/>",
        f"    {origin}",
        *[f"    {e}" for e in extra],
        "  </joint>",
    ]


def _mimic_rows(A: torch.Tensor, b: torch.Tensor) -> dict[int, tuple[int, float, float]]:
    """Model joints a URDF ``<mimic>`` can express: joint ``i`` follows one reading ``k`` alone (``q_i = s r_k +
    b_i``) that an earlier joint ``j`` also follows alone (``q_j = s_j r_k + b_j``), so ``q_i = (s / s_j) q_j + b_i -
    (s / s_j) b_j``. Returns ``i -> (j, multiplier, offset)``."""
    out, owner = {}, {}
    for i in range(A.shape[0]):
        nz = torch.nonzero(A[i]).flatten().tolist()
        if len(nz) != 1:
            continue
        k = nz[0]
        if k not in owner:
            owner[k] = i
            continue
        j = owner[k]
        m = float(A[i, k] / A[j, k])
        out[i] = (j, m, float(b[i] - m * b[j]))
    return out


def _readings_note(robot: RobotModel, A: torch.Tensor, b: torch.Tensor, mimic: dict) -> list[str]:
    """Header lines for a robot whose controller readings are not its joints: a URDF's joints are the model's; the
    map from the readings (calibrated) is written out, and which joints are mimic joints."""
    rows = "; ".join(
        f"{robot.joint_names[i]} = "
        + " + ".join(f"{_num(A[i, k])}*{robot.reading_names[k]}" for k in range(A.shape[1]) if A[i, k] != 0)
        + (f" + {_num(b[i])}" if b[i] != 0 else "")
        for i in range(A.shape[0])
    )
    lines = [
        "The joints below are the model's joints, not the controller's readings. The controller's readings map",
        f"to them as (calibrated): {rows}.",
    ]
    if mimic:
        lines.append("Joints that follow another joint alone are written as <mimic> joints.")
    lines.append("Command the robot through `torchcal compensate`, which writes readings.")
    # the same map for the loader (torchcal.robot.load reads it back, so that the file works as --robot: without it
    # the readings of a measurement file would be taken for the model's joints)
    limits = robot.limits.detach().to("cpu", torch.float64)
    mapping = {
        "readings": list(robot.reading_names),
        "coupling": A.tolist(),
        "offset": b.tolist(),
        "lower": limits[:, 0].tolist(),
        "upper": limits[:, 1].tolist(),
    }
    lines.append(f"{READINGS_MAP_TAG} {json.dumps(mapping, allow_nan=False)}")
    return lines


def write_urdf(
    robot: RobotModel,
    path: str | os.PathLike,
    *,
    probe: bool = True,
    tracker: bool = True,
    name: str | None = None,
    notes: list[str] | None = None,
) -> Path:
    """Write the robot's current (calibrated) geometry, instrument pose and lever arm as a URDF.

    Links: ``robot.link_names`` (base, each moving link, tip), plus ``probe`` fixed to the tip at
    ``t_flange_probe`` and ``tracker`` fixed to the base at ``T_base_tracker = inv(T_tracker_base)``.
    Joints: one revolute or prismatic joint per robot joint, named ``robot.joint_names[i]``, origin ``O_i``; a fixed
    ``<tip>_joint`` with ``O_tip``; ``probe_joint``, ``tracker_joint``. With masses, each moving link
    gets an ``<inertial>`` with its mass and centre of mass (inertia: a placeholder, see
    :data:`PLACEHOLDER_INERTIA`). Effort and velocity limits are written as 0: not calibrated.

    A URDF robot whose source file exists is written as the user's own file with calibrated joint
    origins (:func:`user_urdf_string`; ``name`` then renames nothing unless given).

    Reloading: with the extra leaves, :func:`torchcal.load_robot` picks ``probe`` as the tip (the leaf
    reached through the most joints); pass ``tip_link=<the original tip>`` for ``T_base_flange``.

    Args:
        robot: the robot, its current corrections included.
        path: the ``.urdf`` file to write; written atomically (temporary file, then ``os.replace``).
        probe: add the ``probe`` link.
        tracker: add the ``tracker`` link.
        name: the URDF robot name (default ``robot.name``).
        notes: extra lines for the header comment.

    Returns:
        The path written.
    """
    if not isinstance(robot, RobotModel):
        raise RobotSpecError(f"write_urdf expects a torchcal RobotModel, got {type(robot).__name__}")
    path = Path(path)
    if not path.parent.is_dir():
        raise RobotSpecError(f"{path}: cannot write URDF, directory '{path.parent}' does not exist")
    opts = ExportOptions(probe=probe, tracker=tracker, name=name, notes=tuple(notes or ()))
    if robot.kind == "urdf" and robot.source is not None and Path(robot.source).is_file():
        text = user_urdf_string(robot, opts)
    else:
        text = urdf_string(robot, opts)
    write_text(path, text)
    return path


def write_text(path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a temporary file beside it, flushed to disk, then ``os.replace``): a
    failure leaves nothing written."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# ------------------------------------------------------------------------------ the user's own URDF
def _xml_origin(T: torch.Tensor, near: str | None = None) -> dict[str, str]:
    """xyz/rpy attributes of ``T``; with ``near`` (the file's old rpy), the equivalent rpy triple closest to it.

    ``(r, p, y)`` and ``(r + pi, pi - p, y + pi)`` (each wrapped by 2 pi) are the same rotation; keeping the
    file's own form (e.g. ``pi/2 pi pi``) leaves the diff to the calibration's small change.
    """
    rpy = torch.tensor(exact_rpy(T[:3, :3]), dtype=torch.float64)
    if near is not None:
        ref = torch.tensor([float(v) for v in near.split()], dtype=torch.float64)
        twin = rpy + torch.tensor([math.pi, 0.0, math.pi], dtype=torch.float64)
        twin[1] = math.pi - rpy[1]
        best, best_d = rpy, math.inf
        for cand in (rpy, twin):
            c = ref + torch.remainder(cand - ref + math.pi, 2 * math.pi) - math.pi  # nearest 2 pi wrap
            if _rpy_error(T[:3, :3], c) <= RPY_TOLERANCE * 4 and float((c - ref).abs().max()) < best_d:
                best, best_d = c, float((c - ref).abs().max())
        rpy = best
    return {"xyz": _vec(T[:3, 3]), "rpy": _vec(rpy)}


def _origin_matrix(el) -> torch.Tensor:
    """``(4, 4)`` of a URDF ``<origin>`` element (None: identity)."""
    if el is None:
        return torch.eye(4, dtype=torch.float64)
    xyz = [float(v) for v in el.get("xyz", "0 0 0").split()]
    rpy = [float(v) for v in el.get("rpy", "0 0 0").split()]
    return tf.homogeneous(
        tf.rpy_to_matrix(torch.tensor(rpy, dtype=torch.float64)), torch.tensor(xyz, dtype=torch.float64)
    )


def user_urdf_string(robot: RobotModel, options: ExportOptions | None = None) -> str:
    """The robot's own URDF file (``robot.source``) with calibrated joint origins and added probe/tracker frames.

    Only the ``<origin>`` of the movable joints between ``robot.base_link`` and ``robot.tip_link`` changes:
    with ``P_i`` the product of the fixed joints in front of joint ``i`` (the loader folds them into
    ``O_i``), the new origin is ``inv(P_i) @ O_i``, so the file's FK equals the model's to rounding. The
    XML is edited in place (ElementTree, comments kept), so everything the loader does not model survives.

    Raises:
        RobotSpecError: the file does not hold the robot's chain any more, or the added frame names clash.
    """
    opts = options or ExportOptions()
    src = Path(robot.source)
    raw, root = _read_source_xml(src)
    joints = {j.get("name"): j for j in root.findall("joint")}
    links = {lk.get("name") for lk in root.findall("link")}
    chain = _source_chain(src, root, robot)
    O, T_base_tracker, t_flange_probe = _calibrated(robot)
    _set_origins(chain, O)
    if opts.probe:
        _add_frame(src, root, joints, links, "probe", robot.tip_link, tf.translation(t_flange_probe))
    if opts.tracker:
        _add_frame(src, root, joints, links, "tracker", robot.base_link, T_base_tracker)
    if opts.name is not None:
        root.set("name", opts.name)
    return _user_urdf_text(robot, opts, src, raw, root)


def _read_source_xml(src: Path):
    """The file's text and its XML tree, comments kept and its namespaces' prefixes registered for writing."""
    import xml.etree.ElementTree as ET

    # read again after the fit: the file may have been replaced meanwhile (by a FIFO, a huge file): bounded
    from torchcal._inputs import read_bounded
    from torchcal.robot.load import MAX_DESCRIPTION_BYTES

    data = read_bounded(src, "robot description", lambda m: RobotSpecError(f"{src}: {m}"), limit=MAX_DESCRIPTION_BYTES)
    try:
        raw = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise RobotSpecError(f"{src}: is no longer UTF-8 text (byte offset {e.start})") from None
    for _, (prefix, uri) in ET.iterparse(io.BytesIO(data), events=("start-ns",)):
        ET.register_namespace(prefix, uri)
    return raw, ET.fromstring(raw, parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))


def _source_chain(src: Path, root, robot: RobotModel) -> list:
    """The file's joints from ``robot.base_link`` to ``robot.tip_link``, base first; refused unless its movable
    joints are the robot's."""
    by_child = {j.find("child").get("link"): j for j in root.findall("joint") if j.find("child") is not None}
    chain, link = [], robot.tip_link
    while link != robot.base_link:
        if link not in by_child:
            raise RobotSpecError(
                f"{src}: no joint leads to link '{link}' on the way from '{robot.tip_link}' to "
                f"'{robot.base_link}'; the file no longer holds the calibrated chain"
            )
        chain.append(by_child[link])
        link = by_child[link].find("parent").get("link")
    chain.reverse()
    movable = [j for j in chain if j.get("type") != "fixed"]
    if [j.get("name") for j in movable] != list(robot.joint_names):
        raise RobotSpecError(
            f"{src}: the chain's movable joints {[j.get('name') for j in movable]} are not the "
            f"robot's {list(robot.joint_names)}; the file no longer holds the calibrated chain"
        )
    return chain


def _set_origins(chain: list, O: torch.Tensor) -> None:
    """Each movable joint's ``<origin>`` set to ``inv(P_i) @ O_i``, ``P_i`` the fixed joints in front of it."""
    import xml.etree.ElementTree as ET

    pending = torch.eye(4, dtype=torch.float64)
    i = 0
    for j in chain:
        if j.get("type") == "fixed":
            pending = pending @ _origin_matrix(j.find("origin"))
            continue
        new = tf.invert(pending) @ O[i]
        el = j.find("origin")
        if el is None:
            el = ET.Element("origin")
            j.insert(2, el)
            el.tail = "\n    "
        old_rpy = el.get("rpy")
        el.attrib.clear()
        el.attrib.update(_xml_origin(new, near=old_rpy))
        pending = torch.eye(4, dtype=torch.float64)
        i += 1


def _add_frame(src: Path, root, joints: dict, links: set, kind: str, parent: str, T: torch.Tensor) -> None:
    """The ``probe`` or ``tracker`` link and its fixed joint appended to the file (a previous export's updated)."""
    import xml.etree.ElementTree as ET

    jname, lname = f"{kind}_joint", kind
    old = joints.get(jname)
    if old is not None and old.find("child").get("link") == lname and old.find("parent").get("link") == parent:
        old.find("origin").attrib.update(_xml_origin(T))  # a previous torchcal export: update in place
        return
    if old is not None or lname in links:
        raise RobotSpecError(
            f"{src}: cannot add the '{lname}' frame: the file already has a "
            f"{'joint' if old is not None else 'link'} of that name; pass {kind}=False"
        )
    tail = root[-1].tail if len(root) else "\n"
    if len(root):
        root[-1].tail = "\n  "
    what = (
        "lever arm t_flange_probe (probe position)"
        if kind == "probe"
        else "instrument pose, T_base_tracker = inv(T_tracker_base)"
    )
    c = ET.Comment(f" added by torchcal: the calibrated {what} ")
    c.tail = "\n  "
    lk = ET.Element("link", {"name": lname})
    lk.tail = "\n  "
    jt = ET.Element("joint", {"name": jname, "type": "fixed"})
    jt.text = "\n    "
    for k, (tag, attrs) in enumerate(
        (("parent", {"link": parent}), ("child", {"link": lname}), ("origin", _xml_origin(T)))
    ):
        e = ET.SubElement(jt, tag, attrs)
        e.tail = "\n    " if k < 2 else "\n  "
    jt.tail = tail
    root.extend([c, lk, jt])


def _user_urdf_text(robot: RobotModel, opts: ExportOptions, src: Path, raw: str, root) -> str:
    """The edited tree as text, behind a header comment and the original file's prolog, start tag kept."""
    import re
    import xml.etree.ElementTree as ET

    from torchcal._version import __version__

    # keep the comments in front of <robot>: licence and provenance notices of the original file
    prolog = raw[: raw.find("<robot")] if "<robot" in raw else ""
    prolog = re.sub(r"<\?xml[^>]*\?>\s*", "", prolog).strip()
    header = [
        f"Written by torchcal {__version__}: the calibrated robot '{robot.name}', in its own URDF ({src.name}).",
        f"Changed: the origins of the movable joints {', '.join(robot.joint_names)} (calibrated values, "
        "repr() floats).",
        "Everything else is the original file's. Added frames: 'probe' (the calibrated lever arm, fixed to "
        f"'{robot.tip_link}') and 'tracker' (the instrument pose, fixed to '{robot.base_link}')."
        if opts.probe and opts.tracker
        else "",
        *opts.notes,
    ]
    out = ['<?xml version="1.0"?>', "<!--", *[f"  {_comment(line)}" for line in header if line], "-->"]
    if prolog:
        out.append(prolog)
    # ElementTree writes empty elements as "<x />": back to the usual "<x/>", to keep the diff to the origins
    body = ET.tostring(root, encoding="unicode").replace(" />", "/>")
    start = re.search(r"<robot\b[^>]*>", raw)
    if opts.name is None and start is not None:
        # the original start tag, with namespace declarations ElementTree drops when nothing uses them
        body = re.sub(r"<robot\b[^>]*>", lambda _: start.group(0), body, count=1)
    out.append(body)
    return "\n".join(out) + "\n"
