"""Robot descriptions -> :class:`RobotModel`: built-in names, DH tables in YAML, URDF files."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchcal.errors import OptionError, RobotSpecError
from torchcal.robot.model import DHConvention, DHGeometry, RobotModel, URDFGeometry
from torchcal.robot.readings import MAX_RATIO, MIN_RATIO, READINGS_MAP_TAG, Readings, check_coupling

#: Largest robot description file accepted [bytes]: real URDFs and DH tables are kilobytes.
MAX_DESCRIPTION_BYTES = 8 * 1024 * 1024


def _robots_dir() -> Path:
    """The built-in descriptions: ``TORCHCAL_ROBOTS``, else the package data ``torchcal/robots`` of an
    installed wheel, else the source tree's top-level ``robots/`` (checkouts and editable installs)."""
    if "TORCHCAL_ROBOTS" in os.environ:
        return Path(os.environ["TORCHCAL_ROBOTS"])
    from importlib.resources import files

    packaged = files("torchcal") / "robots"
    if packaged.is_dir():
        return Path(str(packaged))
    return Path(__file__).resolve().parents[2] / "robots"


#: Where the built-in robot descriptions live (see :func:`_robots_dir`).
ROBOTS_DIR = _robots_dir()


def builtin_robots() -> list[str]:
    """Names accepted by :func:`load_robot` besides paths (``ur5``, ``ur10``, ``panda``, ``ur5.urdf``, ...)."""
    if not ROBOTS_DIR.is_dir():
        return []
    files = sorted(p for p in ROBOTS_DIR.iterdir() if p.suffix in (".yaml", ".yml", ".urdf"))
    return sorted({p.stem for p in files} | {p.name for p in files})


def resolve_robot_spec(spec: str | os.PathLike) -> Path:
    """Turn a built-in name or a path into the description file, or raise listing the valid names."""
    path = Path(spec)
    if path.suffix in (".yaml", ".yml", ".urdf") and path.is_file():
        return path
    if path.exists() and not path.is_file() and not path.is_dir():  # a FIFO or a device: never opened
        from torchcal._inputs import kind_of

        raise RobotSpecError(
            f"{path}: is {kind_of(path.stat().st_mode)}, not a regular file; give a robot description file"
        )
    if path.is_file():
        raise RobotSpecError(f"{path}: unknown robot description type '{path.suffix}', expected .urdf, .yaml or .yml")
    name = str(spec)
    for candidate in (
        ROBOTS_DIR / name,
        ROBOTS_DIR / f"{name}.yaml",
        ROBOTS_DIR / f"{name}.yml",
        ROBOTS_DIR / f"{name}.urdf",
    ):
        if candidate.is_file() and candidate.suffix in (".yaml", ".yml", ".urdf"):
            return candidate
    raise RobotSpecError(
        f"robot '{spec}' is neither a file nor a built-in robot; built-ins: {', '.join(builtin_robots()) or 'none'}"
    )


def load_robot(
    spec: str | os.PathLike,
    *,
    base_link: str | None = None,
    tip_link: str | None = None,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
    reader: str = "yourdfpy",
) -> RobotModel:
    """Load a robot: a built-in name (``ur5``, ``ur10``, ``panda``), a URDF path or a DH YAML path.

    Args:
        spec: built-in name or path.
        base_link, tip_link: URDF only, pick the chain when the tree has several.
        dtype: must be float64 (the calibration path is float64).
        device: ``cpu``, ``cuda`` or ``cuda:N``, checked to exist here.
        reader: how a URDF is read (:func:`load_urdf`).

    Returns:
        A :class:`RobotModel` with nominal geometry and zero corrections.

    Raises:
        OptionError: a device this machine or this torch build does not have (torch's own ``AssertionError`` of a
            CPU-only build otherwise).
    """
    from torchcal._device import resolve_device

    device = resolve_device(device)
    path = resolve_robot_spec(spec)
    if path.suffix == ".urdf":
        return load_urdf(path, base_link=base_link, tip_link=tip_link, dtype=dtype, device=device, reader=reader)
    if base_link or tip_link:
        raise RobotSpecError(
            f"{path}: base_link/tip_link (--base-link/--tip-link) apply to URDF robots only, this is a DH table"
        )
    return load_dh_yaml(path, dtype=dtype, device=device)


# --------------------------------------------------------------------------- DH
def _read_description(path: Path) -> bytes:
    """The file's bytes, refusing what is not a regular file (a FIFO, /dev/zero) and files beyond
    :data:`MAX_DESCRIPTION_BYTES`, before reading."""
    from torchcal._inputs import read_bounded

    return read_bounded(
        path, "robot description", lambda message: RobotSpecError(f"{path}: {message}"), limit=MAX_DESCRIPTION_BYTES
    )


def _decode(path: Path, raw: bytes) -> str:
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise RobotSpecError(
            f"{path}, line {line}: not UTF-8 text (byte 0x{raw[e.start]:02x} at offset "
            f"{e.start}); save the file as UTF-8"
        ) from None


def _number(path, where: str, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RobotSpecError(f"{path}: {where}: '{key}' must be a number, got {value!r}")
    if not math.isfinite(value):
        raise RobotSpecError(f"{path}: {where}: '{key}' must be finite, got {value!r}")
    return float(value)


#: YAML 1.2 floats: YAML 1.1 (PyYAML) reads ``1e300`` and ``1.0e300`` without a sign in the exponent as text
_YAML12_FLOAT = r"^(?:[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+|[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?)$"


def _yaml_loader():
    """PyYAML's safe loader that refuses a key given twice in one mapping (YAML forbids it; PyYAML silently keeps
    the last) and reads YAML 1.2 floats (``1e300``, ``1.0e300``) as numbers."""
    import re

    import yaml

    class Loader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen = {}
                for key_node, _ in node.value:
                    key = self.construct_object(key_node, deep=deep)
                    try:
                        first = seen.get(key)
                    except TypeError:  # an unhashable key: the base class says so
                        break
                    if first is not None:
                        raise yaml.constructor.ConstructorError(
                            None,
                            None,
                            f"key {key!r} is given twice in one mapping (first on line {first.line + 1}); "
                            "give each key once",
                            key_node.start_mark,
                        )
                    seen[key] = key_node.start_mark
            return super().construct_mapping(node, deep=deep)

    Loader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(_YAML12_FLOAT), list("-+0123456789."))
    return Loader


def _yaml_error(path: Path, e) -> str:
    """A YAML error as one line: file, line and column of the problem, then what the parser says."""
    mark = getattr(e, "problem_mark", None)
    where = f"{path}" if mark is None else f"{path}, line {mark.line + 1}, column {mark.column + 1}"
    problem = getattr(e, "problem", None) or str(e)
    context = getattr(e, "context", None)
    text = f"{context}: {problem}" if context else problem
    return f"{where}: not valid YAML: {' '.join(str(text).split())}"


#: Joint types a DH table may declare (``type:``): the reading is an angle [rad] or a length [m]
JOINT_TYPES = ("revolute", "prismatic")
#: Default limits of a prismatic joint that declares none [m], as +-2 pi is a revolute joint's: the readings are
#: checked against them, so a default must hold every track and slide (a longer one declares its limits)
PRISMATIC_DEFAULT_REACH = 10.0

#: Largest length [m] and angle [rad] a robot description may hold: a robot is not a kilometre long, and an angle
#: beyond one turn is degrees written as radians (-90 for -pi/2: within 300 prior sigmas of nothing, it passed
#: the wrong-robot stop and bent the fit) or a typo
MAX_DESCRIPTION_LENGTH = 1000.0
MAX_DESCRIPTION_ANGLE = 2 * math.pi + 1e-9


def _safe_name(path, what: str, name) -> str:
    """``name`` as text, refused when it holds control characters (a line break would forge lines in messages)."""
    text = str(name)
    if any(ord(c) < 32 or ord(c) == 127 for c in text):
        raise RobotSpecError(f"{path}: {what} {text!r} holds control characters (line breaks, NUL, ...); rename it")
    return text


def load_dh_yaml(path: str | os.PathLike, *, dtype=torch.float64, device="cpu") -> RobotModel:
    """Load a DH table: ``name``, ``convention``, ``joints: [{a, alpha, d, theta, ...}]``.

    Optional per joint: ``type`` (``revolute``, the default, or ``prismatic``: the reading [m] adds to ``d`` and
    ``theta`` is fixed), ``beta`` [rad] (a tilt about y after alpha, as a calibrated table written back by ``torchcal
    export --format dh`` holds it; default 0), ``lower``, ``upper`` [rad, m for a prismatic joint] (default +-2 pi
    rad, +-1 m), ``mass``
    [kg] and ``com`` [m, in DH frame i] (all joints or none), ``name``. Optional at the top: ``tolerances:
    {length_mm, angle_deg}``, the robot's manufacturing tolerances (the priors of its kinematic calibration; the
    robot's ``tolerances`` attribute, (m, rad), None without them).
    """
    path = Path(path)
    doc = _load_yaml_doc(path)
    if not isinstance(doc, dict) or "joints" not in doc:
        raise RobotSpecError(f"{path}: expected a mapping with 'name', 'convention' and 'joints'")
    conv = str(doc.get("convention", "standard")).lower()
    valid = [c.value for c in DHConvention]
    if conv not in valid:
        raise RobotSpecError(f"{path}: convention '{conv}' is not one of {valid}")
    joints = doc["joints"]
    if not isinstance(joints, list) or not joints:
        raise RobotSpecError(f"{path}: 'joints' must be a non-empty list, base to tip")
    rows: list[_DHJoint] = []
    for i, j in enumerate(joints):
        rows.append(_dh_joint(path, i, j))
        names = [r.name for r in rows[:-1]]
        if rows[-1].name in names:
            raise RobotSpecError(
                f"{path}: joint {i + 1}: name {rows[-1].name!r} is also the name of joint "
                f"{names.index(rows[-1].name) + 1}; joint names must be unique"
            )
    masses = [r.mass for r in rows if r.mass is not None]
    if masses and len(masses) != len(joints):
        raise RobotSpecError(f"{path}: 'mass' is given for {len(masses)} of {len(joints)} joints; give all or none")
    convention = DHConvention(conv)
    geometry = DHGeometry(
        a=[r.a for r in rows],
        alpha=[r.alpha for r in rows],
        d=[r.d for r in rows],
        theta=[r.theta for r in rows],
        convention=convention,
        prismatic=[r.prismatic for r in rows],
        beta=[r.beta for r in rows],
        dtype=dtype,
        device=device,
    )
    limits = torch.tensor([(r.lower, r.upper) for r in rows], dtype=dtype)
    com_t = _dh_coms(geometry, [r.com for r in rows], dtype) if masses else None
    dof = len(joints)
    readings, reading_limits, reading_names = (None, None, None)
    if doc.get("readings") is not None:
        readings, reading_limits, reading_names = _readings_block(path, doc["readings"], dof, dtype)
    robot = RobotModel(
        name=_safe_name(path, "robot name", doc.get("name", path.stem)),
        readings=readings,
        reading_limits=reading_limits,
        reading_names=reading_names,
        geometry=geometry,
        limits=limits,
        joint_names=[r.name for r in rows],
        link_names=["base"] + [f"link{i + 1}" for i in range(dof)] + ["flange"],
        masses=torch.tensor(masses, dtype=dtype) if masses else None,
        coms=com_t,
        source=str(path),
        kind="dh",
        base_link="base",
        tip_link="flange",
        dtype=dtype,
        device=device,
    )
    robot.tolerances = _tolerances(path, doc.get("tolerances"))
    return robot.to(device)


def _load_yaml_doc(path: Path):
    """The YAML document in ``path``, refused before it is built when it nests too deep or uses aliases."""
    import yaml

    from torchcal._inputs import MAX_DEPTH

    text = _decode(path, _read_description(path))
    try:
        # Aliases ('*name') can expand a kilobyte into gigabytes; a DH table never needs them. The composer
        # recurses per level (20,000 nested '[' cost a minute, then a RecursionError); the event stream does
        # not, so the depth is bounded here first.
        depth = 0
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    mark = event.start_mark
                    raise RobotSpecError(
                        f"{path}, line {mark.line + 1}, column {mark.column + 1}: nested more than {MAX_DEPTH} "
                        "levels deep; a DH table nests three"
                    )
            elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
                depth -= 1
            elif isinstance(event, yaml.AliasEvent):
                mark = event.start_mark
                raise RobotSpecError(
                    f"{path}, line {mark.line + 1}, column {mark.column + 1}: YAML aliases "
                    "('*name') are not accepted in a robot description; write the values out"
                )
        return yaml.load(text, Loader=_yaml_loader())
    except yaml.YAMLError as e:
        raise RobotSpecError(_yaml_error(path, e)) from None


_DH_KEYS = {"a", "alpha", "d", "theta", "beta", "lower", "upper", "mass", "com", "name", "type"}
#: the largest manufacturing tolerance a robot file may declare: beyond it the prior no longer holds a geometry the
#: rows cannot tell near its nominal value, and 'tolerance' is likely in the wrong unit
MAX_TOLERANCE_MM, MAX_TOLERANCE_DEG = 10.0, 1.0


def _tolerances(path: Path, block) -> tuple[float, float] | None:
    """A DH table's ``tolerances: {length_mm, angle_deg}``: the robot's manufacturing tolerances, the priors of its
    kinematic calibration (:meth:`torchcal.pipeline.options.FitSettings.geometric`), as ``(m, rad)``; None where the
    file gives none."""
    if block is None:
        return None
    where = "tolerances"
    if not isinstance(block, dict) or set(block) != {"length_mm", "angle_deg"}:
        raise RobotSpecError(
            f"{path}: '{where}' must be a mapping with length_mm and angle_deg (the manufacturing tolerances of the "
            f"geometry, the priors of its kinematic calibration), got {block!r}"
        )
    length, angle = (_number(path, where, k, block[k]) for k in ("length_mm", "angle_deg"))
    for key, value, cap in (("length_mm", length, MAX_TOLERANCE_MM), ("angle_deg", angle, MAX_TOLERANCE_DEG)):
        if not 0 < value <= cap:
            raise RobotSpecError(f"{path}: {where}: '{key}' = {value!r} must be above 0 and at most {cap}")
    return length * 1e-3, math.radians(angle)


@dataclass
class _DHJoint:
    """One row of a DH table, checked: lengths [m], angles [rad], limits [rad, m], mass [kg] and com [m] or None."""

    a: float
    alpha: float
    d: float
    theta: float
    beta: float
    prismatic: bool
    lower: float
    upper: float
    mass: float | None
    com: list[float] | None
    name: str


def _dh_joint(path: Path, i: int, j) -> _DHJoint:
    """Row ``i`` (from 0) of a DH table's ``joints``, each entry checked in the order a reader fixes them."""
    where = f"joint {i + 1}"
    if not isinstance(j, dict):
        raise RobotSpecError(f"{path}: {where}: expected a mapping like {{a: .., alpha: .., d: .., theta: ..}}")
    unknown = set(j) - _DH_KEYS
    if unknown:
        raise RobotSpecError(
            f"{path}: {where}: unknown keys {sorted(unknown)}; valid: a, alpha, d, theta, beta, "
            "lower, upper, mass, com, name, type"
        )
    beta = _number(path, where, "beta", j.get("beta", 0.0))
    if abs(beta) > MAX_DESCRIPTION_ANGLE:
        raise RobotSpecError(
            f"{path}: {where}: 'beta' = {j['beta']!r} rad is beyond {MAX_DESCRIPTION_ANGLE:.4g} rad (in degrees?)"
        )
    kind = j.get("type", "revolute")
    if kind not in JOINT_TYPES:
        raise RobotSpecError(f"{path}: {where}: type {kind!r} is not one of {', '.join(JOINT_TYPES)}")
    dh = {}
    for key in ("a", "alpha", "d", "theta"):
        if key not in j:
            raise RobotSpecError(f"{path}: {where}: missing '{key}'")
        dh[key] = _number(path, where, key, j[key])
        bound = MAX_DESCRIPTION_LENGTH if key in ("a", "d") else MAX_DESCRIPTION_ANGLE
        if abs(dh[key]) > bound:
            unit = "m" if key in ("a", "d") else "rad"
            raise RobotSpecError(
                f"{path}: {where}: '{key}' = {j[key]!r} {unit} is beyond {bound:.4g} {unit}; lengths are metres and "
                "angles radians" + (" (a value in degrees?)" if unit == "rad" else "")
            )
    reach = PRISMATIC_DEFAULT_REACH if kind == "prismatic" else 2 * math.pi
    lower = _number(path, where, "lower", j.get("lower", -reach))
    upper = _number(path, where, "upper", j.get("upper", reach))
    if lower >= upper:
        raise RobotSpecError(f"{path}: {where}: lower limit {lower} is not below upper {upper}")
    mass = com = None
    if "mass" in j:
        mass = _number(path, where, "mass", j["mass"])
        com = j.get("com", [0.0, 0.0, 0.0])
        if not isinstance(com, list) or len(com) != 3:
            raise RobotSpecError(f"{path}: {where}: 'com' must be a list of 3 numbers [m]")
        com = [_number(path, where, "com", c) for c in com]
    name = _safe_name(path, f"{where}: name", j.get("name", f"joint{i + 1}"))
    return _DHJoint(
        **dh, beta=beta, prismatic=kind == "prismatic", lower=lower, upper=upper, mass=mass, com=com, name=name
    )


def _dh_coms(geometry: DHGeometry, coms: list, dtype) -> torch.Tensor:
    """Centres of mass given in DH frame i, moved to the frame that rotates with joint i (F_i), where the model
    keeps them. Standard DH: frame i = F_i @ M_i; modified: frame i = F_i."""
    com_t = torch.tensor(coms, dtype=dtype)
    if geometry.convention is DHConvention.STANDARD:
        M = geometry.origins()[1:].detach()
        com_t = (M[:, :3, :3] @ com_t.unsqueeze(-1)).squeeze(-1) + M[:, :3, 3]
    return com_t


def _readings_block(path: Path, block, n_joints: int, dtype):
    """The ``readings:`` block of a DH table: ``coupling`` (n_joints x n_readings), optional ``offset`` (n_joints,
    rad), ``lower``/``upper`` (n_readings,, rad) and ``names``. Model joint ``i = sum_k coupling[i][k] reading_k +
    offset[i]``; the coupling's declared non-zero entries are ratios the calibration may correct."""
    where = "readings"
    if not isinstance(block, dict):
        raise RobotSpecError(f"{path}: '{where}' must be a mapping with 'coupling' and optional 'offset'")
    unknown = set(block) - {"coupling", "offset", "lower", "upper", "names"}
    if unknown:
        raise RobotSpecError(
            f"{path}: '{where}': unknown keys {sorted(unknown)}; valid: coupling, offset, lower, upper, names"
        )
    rows = block.get("coupling")
    if not isinstance(rows, list) or not rows or not all(isinstance(r, list) for r in rows):
        raise RobotSpecError(
            f"{path}: '{where}.coupling' must be a list of {n_joints} rows (one per model joint), each a list of "
            "numbers (one per reading)"
        )
    width = {len(r) for r in rows}
    if len(width) != 1:
        raise RobotSpecError(f"{path}: '{where}.coupling' rows have different lengths {sorted(width)}")
    A = [[_number(path, f"{where}.coupling row {i + 1}", f"column {k + 1}", v) for k, v in enumerate(r)]
         for i, r in enumerate(rows)]  # fmt: skip
    why = check_coupling(A, n_joints, f"'{where}.coupling'")
    if why:
        raise RobotSpecError(f"{path}: {why}")
    n_read = len(A[0])

    def vector(key: str, n: int, default):
        v = block.get(key, default)
        if not isinstance(v, list) or len(v) != n:
            raise RobotSpecError(f"{path}: '{where}.{key}' must be a list of {n} numbers [rad]")
        out = [_number(path, where, key, x) for x in v]
        if key == "offset" and any(abs(x) > MAX_DESCRIPTION_ANGLE for x in out):
            raise RobotSpecError(
                f"{path}: '{where}.offset' is beyond {MAX_DESCRIPTION_ANGLE:g} rad; angles are radians"
            )
        return out

    offset = vector("offset", n_joints, [0.0] * n_joints)
    limits = None
    if "lower" in block or "upper" in block:
        lower = vector("lower", n_read, [-2 * math.pi] * n_read)
        upper = vector("upper", n_read, [2 * math.pi] * n_read)
        for k, (lo, hi) in enumerate(zip(lower, upper)):
            if lo >= hi:
                raise RobotSpecError(f"{path}: '{where}': reading {k + 1}: lower limit {lo} is not below upper {hi}")
        limits = torch.tensor(list(zip(lower, upper)), dtype=dtype)
    names = None
    if "names" in block:
        v = block["names"]
        if not isinstance(v, list) or len(v) != n_read:
            raise RobotSpecError(f"{path}: '{where}.names' must be a list of {n_read} names")
        names = [_safe_name(path, f"{where}.names", x) for x in v]
        if len(set(names)) != n_read:
            raise RobotSpecError(f"{path}: '{where}.names' must be unique")
    At = torch.tensor(A, dtype=dtype)
    readings = Readings(At, torch.tensor(offset, dtype=dtype), free=At != 0, dtype=dtype)
    return readings, limits, names


# ------------------------------------------------------------------------- URDF
_MOVABLE = ("revolute", "continuous", "prismatic")


def load_urdf(
    path: str | os.PathLike,
    *,
    base_link: str | None = None,
    tip_link: str | None = None,
    dtype=torch.float64,
    device="cpu",
    reader: str = "yourdfpy",
) -> RobotModel:
    """Load a serial chain from a URDF with yourdfpy, in float64, meshes not loaded.

    The chain runs from ``base_link`` (default: the root) to ``tip_link`` (default: the leaf
    reached through the most movable joints; ambiguous trees must name it). Fixed joints
    are folded into the neighbouring origins; revolute, continuous and prismatic joints are the
    robot's joints (a prismatic joint's reading and limits are metres).

    Args:
        reader: ``"yourdfpy"`` (default: the maintained parser and its checks) or ``"elements"``: the joints,
            links and inertials read from the XML elements as yourdfpy reads them (:func:`_urdf_elements`, the
            same numbers to the bit) without importing yourdfpy and its mesh library (trimesh, scipy, networkx:
            about a second and tens of MB). For files torchcal wrote itself, such as the round-trip check of a
            calibrated URDF (:func:`torchcal.report.urdf.urdf_fk_difference`); it parses with the standard library's
            ``xml.etree`` (already loaded) instead of lxml.
    """
    if reader not in ("yourdfpy", "elements"):
        raise OptionError(f"reader must be 'yourdfpy' or 'elements', got {reader!r}")

    path = Path(path)
    raw = _read_description(path)
    urdf = _parse_urdf(path, raw, reader)
    child_of, children, links = _urdf_tree(path, urdf)
    base_link = _pick_base_link(path, links, child_of, base_link)
    tip_link = _pick_tip_link(path, links, children, child_of, base_link, tip_link)
    chain = _joints_to(path, child_of, base_link, tip_link)
    if not chain:
        raise RobotSpecError(f"{path}: tip link '{tip_link}' is not below base link '{base_link}'")
    joints = _chain_joints(path, chain, base_link, tip_link)
    masses, coms = _chain_bodies(urdf, chain, len(joints.names))

    movable = {j.name: j for j in urdf.robot.joints if j.type in _MOVABLE}
    mimics = joints.mimics
    readings, reading_names = _mimic_readings(path, joints.names, mimics, movable, dtype) if mimics else (None, None)
    reading_limits = None
    written = _written_map(path, raw, joints.names, dtype)
    if written is not None:  # a DH robot's readings map, as torchcal wrote it: the <mimic> tags are part of it
        readings, reading_limits, reading_names = written
    geometry = URDFGeometry(
        origins=torch.tensor(np.stack(joints.origins), dtype=dtype),
        axes=torch.tensor(np.stack(joints.axes), dtype=dtype),
        joint_names=joints.names,
        prismatic=joints.prismatic,
        dtype=dtype,
        device=device,
    )
    return RobotModel(
        name=urdf.robot.name or path.stem,
        geometry=geometry,
        limits=torch.tensor(joints.limits, dtype=dtype),
        joint_names=joints.names,
        link_names=joints.link_names,
        masses=None if masses is None else torch.tensor(masses, dtype=dtype),
        coms=None if coms is None else torch.tensor(np.stack(coms), dtype=dtype),
        source=str(path),
        kind="urdf",
        base_link=base_link,
        tip_link=tip_link,
        readings=readings,
        reading_limits=reading_limits,
        reading_names=reading_names,
        dtype=dtype,
        device=device,
    ).to(device)


def _parse_urdf(path: Path, raw: bytes, reader: str):
    """The file's ``<robot>``, its elements checked, as yourdfpy's URDF object (or :func:`_urdf_elements`' twin)."""
    tree = _parse_stdlib(path, raw) if reader == "elements" else _parse_lxml(path, raw)
    if tree.tag != "robot":
        raise RobotSpecError(f"{path}: the root element is <{tree.tag}>, expected <robot>")
    _check_urdf_elements(path, tree)
    if reader == "elements":
        return _urdf_elements(path, tree)
    import io

    import yourdfpy

    try:
        return yourdfpy.URDF.load(
            io.BytesIO(raw),
            load_meshes=False,
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_collision_meshes=False,
            mesh_dir=str(path.parent),
        )
    except Exception as e:  # yourdfpy raises assorted exception types on malformed files
        raise RobotSpecError(f"{path}: cannot parse URDF: {type(e).__name__}: {e}") from None


def _urdf_tree(path: Path, urdf) -> tuple[dict, dict[str, list], list[str]]:
    """The joint leading to each link, the joints leaving each link and the link names; refused unless a tree."""
    joints = urdf.robot.joints
    child_of = {}
    for j in joints:
        if j.child in child_of:
            raise RobotSpecError(
                f"{path}: link '{j.child}' is the child of two joints, '{child_of[j.child].name}' "
                f"and '{j.name}'; a URDF is a tree"
            )
        child_of[j.child] = j
    children: dict[str, list] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)
    links = [lk.name for lk in urdf.robot.links]
    # a URDF is a tree: following parents from any link must end at a root, never come back
    done: set[str] = set()
    for start in links:
        trail, link = [], start
        while link in child_of and link not in done:
            if link in trail:
                cycle = " -> ".join(trail[trail.index(link) :] + [link])
                raise RobotSpecError(f"{path}: the links form a cycle ({cycle}); a URDF must be a tree")
            trail.append(link)
            link = child_of[link].parent
        done.update(trail)
    return child_of, children, links


def _pick_base_link(path: Path, links: list[str], child_of: dict, base_link: str | None) -> str:
    """The base link asked for, checked, or the tree's only root."""
    roots = [lk for lk in links if lk not in child_of]
    if base_link is None:
        if len(roots) != 1:
            raise RobotSpecError(
                f"{path}: the URDF has {len(roots)} root links {roots}; pick one with base_link (--base-link)"
            )
        return roots[0]
    if base_link not in links:
        raise RobotSpecError(f"{path}: base link '{base_link}' not found; links: {', '.join(links)}")
    return base_link


def _joints_to(path: Path, child_of: dict, base_link: str, link: str) -> list:
    """The joints from ``base_link`` down to ``link``, base first; empty when ``link`` is not below the base."""
    out, seen = [], {link}
    while link != base_link:
        if link not in child_of:
            return []
        j = child_of[link]
        out.append(j)
        link = j.parent
        if link in seen:
            cycle = " -> ".join([jj.child for jj in out] + [link])
            raise RobotSpecError(f"{path}: the links form a cycle ({cycle}); a URDF is a tree")
        seen.add(link)
    return out[::-1]


def _pick_tip_link(path: Path, links: list[str], children: dict, child_of: dict, base_link: str, tip_link) -> str:
    """The tip link asked for, checked, or the one leaf below the base behind the most movable joints."""
    if tip_link is not None:
        if tip_link not in links:
            raise RobotSpecError(f"{path}: tip link '{tip_link}' not found; links: {', '.join(links)}")
        return tip_link

    def n_movable(link):
        return sum(j.type in _MOVABLE for j in _joints_to(path, child_of, base_link, link))

    leaves = [
        lk for lk in links if lk not in children and (lk == base_link or _joints_to(path, child_of, base_link, lk))
    ]
    best = max((n_movable(lk) for lk in leaves), default=0)
    cands = [lk for lk in leaves if n_movable(lk) == best]
    if best == 0 or len(cands) != 1:
        raise RobotSpecError(
            f"{path}: cannot choose the tip link: leaves {cands} each end a chain of {best} "
            "joints; pick one with tip_link (--tip-link)"
        )
    return cands[0]


@dataclass
class _ChainJoints:
    """The movable joints of a URDF chain: origins (fixed joints folded in, plus the tip's), unit axes, limits,
    names, the link each moves (base first, tip last), which are prismatic, and their ``<mimic>`` tags."""

    origins: list = field(default_factory=list)
    axes: list = field(default_factory=list)
    limits: list = field(default_factory=list)
    names: list = field(default_factory=list)
    link_names: list = field(default_factory=list)
    prismatic: list = field(default_factory=list)
    mimics: dict = field(default_factory=dict)  # joint name -> its <mimic> (joint, multiplier, offset)


def _chain_joints(path: Path, chain: list, base_link: str, tip_link: str) -> _ChainJoints:
    """The chain's movable joints, each fixed joint folded into the next movable joint's origin (or the tip's)."""
    out = _ChainJoints(link_names=[base_link])
    pending = np.eye(4)
    for j in chain:
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
        if not np.isfinite(origin).all():
            raise RobotSpecError(
                f"{path}: joint '{j.name}': the origin has non-finite values (xyz/rpy must be finite numbers)"
            )
        if j.type == "fixed":
            pending = pending @ origin
            continue
        if j.type not in _MOVABLE:
            raise RobotSpecError(
                f"{path}: joint '{j.name}' is {j.type}; torchcal supports revolute, continuous and prismatic joints"
            )
        if getattr(j, "mimic", None) is not None:
            out.mimics[j.name] = j.mimic
        out.origins.append(pending @ origin)
        pending = np.eye(4)
        out.axes.append(_joint_axis(path, j))
        out.limits.append(_joint_limits(path, j))
        out.names.append(j.name)
        out.link_names.append(j.child)
        out.prismatic.append(j.type == "prismatic")
    if not out.origins:
        raise RobotSpecError(f"{path}: no movable joint between '{base_link}' and '{tip_link}'")
    out.origins.append(pending)
    out.link_names.append(tip_link)
    return out


def _joint_axis(path: Path, j) -> np.ndarray:
    """The joint's axis as a unit vector (URDF's default x when it gives none)."""
    axis = np.asarray(j.axis if j.axis is not None else [1.0, 0.0, 0.0], dtype=np.float64)
    norm = float(np.linalg.norm(axis)) if np.isfinite(axis).all() else float("nan")
    if not norm > 1e-12:
        raise RobotSpecError(
            f"{path}: joint '{j.name}': axis xyz=\"{' '.join(map(str, axis))}\" is not a "
            'direction; expected a finite non-zero vector such as "0 0 1"'
        )
    return axis / norm


def _joint_limits(path: Path, j) -> tuple[float, float]:
    """The joint's (lower, upper) [rad, m]: none for a continuous joint, the default reach where the file has none."""
    if j.type == "continuous":
        # no limit at all: readings past one turn are fine (and not taken for degrees)
        return (-math.inf, math.inf)
    if j.limit is None or j.limit.lower is None or j.limit.upper is None:
        reach = PRISMATIC_DEFAULT_REACH if j.type == "prismatic" else 2 * math.pi
        return (-reach, reach)
    lo, hi = float(j.limit.lower), float(j.limit.upper)
    if math.isnan(lo) or math.isnan(hi) or lo > hi:
        raise RobotSpecError(f"{path}: joint '{j.name}': limit lower={lo} upper={hi}; lower must not be above upper")
    return (lo, hi)


def _chain_bodies(urdf, chain: list, dof: int) -> tuple[list | None, list | None]:
    """Mass and centre of mass of each moving body, or (None, None) when no link on the chain has a mass.

    Each moving body is the child link of a joint plus every link fixed to it before the next movable joint (on
    the chain); its centre of mass is in the joint's child frame."""
    link_by_name = {lk.name: lk for lk in urdf.robot.links}
    movable_idx = -1
    body_m = [0.0] * dof
    body_c = [np.zeros(3) for _ in range(dof)]
    offset = np.eye(4)
    have_inertia = False
    for j in chain:
        if j.type == "fixed":
            if movable_idx < 0:
                continue
            offset = offset @ (np.eye(4) if j.origin is None else j.origin)
        else:
            movable_idx += 1
            offset = np.eye(4)
        if movable_idx < 0:
            continue
        inertial = link_by_name[j.child].inertial
        if inertial is not None and inertial.mass:
            have_inertia = True
            c_link = np.zeros(3) if inertial.origin is None else np.asarray(inertial.origin)[:3, 3]
            c = offset[:3, :3] @ c_link + offset[:3, 3]
            m = float(inertial.mass)
            total = body_m[movable_idx] + m
            body_c[movable_idx] = (body_c[movable_idx] * body_m[movable_idx] + c * m) / total
            body_m[movable_idx] = total
    return (body_m, body_c) if have_inertia else (None, None)


def _written_map(path: Path, raw: bytes, jnames: list[str], dtype) -> tuple[Readings, torch.Tensor, list[str]] | None:
    """The readings map a URDF torchcal wrote for a DH robot with a ``readings:`` block carries in its header
    (:data:`~torchcal.robot.readings.READINGS_MAP_TAG`): the readings, the map as calibrated (its non-zero ratios free
    again, as the block's are) and the readings' limits; None for any other file.

    Without it a run's ``robot_calibrated.urdf`` of a parallelogram arm would take the file's readings for the
    model's joints (the ``<mimic>`` tags can say only the rows that follow one reading).
    """
    if not _written_by_torchcal(raw):
        return None
    tag = READINGS_MAP_TAG.encode()
    at = raw.find(tag)
    if at < 0:
        if b"The controller's readings map" in raw:
            raise RobotSpecError(
                f"{path}: this URDF was written by an older torchcal for a robot whose readings are not its joints, "
                "and its header does not carry the readings map in a form that can be read back; calibrate with the "
                "robot's own description (the DH table with its readings: block)"
            )
        return None
    line = raw[at + len(tag) :].split(b"\n", 1)[0]
    try:
        doc = json.loads(line)
        A = torch.tensor(doc["coupling"], dtype=dtype)
        b = torch.tensor(doc["offset"], dtype=dtype)
        limits = torch.tensor(list(zip(doc["lower"], doc["upper"])), dtype=dtype)
        names = [_safe_name(path, "reading name", n) for n in doc["readings"]]
    except (ValueError, KeyError, TypeError, RuntimeError) as e:
        raise RobotSpecError(f"{path}: the header's readings map cannot be read ({type(e).__name__}: {e})") from None
    why = check_coupling(A.tolist(), len(jnames), "the header's readings map")
    if why is None and (b.shape != (len(jnames),) or limits.shape != (A.shape[1], 2) or len(names) != A.shape[1]):
        why = f"the header's readings map does not fit the chain's {len(jnames)} joints"
    if why:
        raise RobotSpecError(f"{path}: {why}")
    return Readings(A, b, free=A != 0, dtype=dtype), limits, names


def _mimic_readings(path: Path, jnames: list[str], mimics: dict, movable: dict, dtype) -> tuple[Readings, list[str]]:
    """The readings map of a chain with mimic joints: one reading per joint that mimics none, a mimic joint's row
    ``multiplier`` at its source's reading and ``offset`` in ``b`` (a mimic of a mimic composes the two).

    A source off the chain (``movable``: every movable joint of the URDF by name), such as the virtual joint on a side
    branch that vendors drive a lifting column's mimicking segments with, takes a reading too: it moves no link of the
    chain itself, but the controller reports it. Its reading comes where its first mimic joint is in the chain.
    """
    mimics = dict(mimics)
    for name, j in movable.items():  # an off-chain source may itself mimic another joint
        if name not in jnames and getattr(j, "mimic", None) is not None:
            mimics[name] = j.mimic
    rows = [_mimic_row(path, name, jnames, mimics, movable) for name in jnames]
    readers: list[str] = []
    for name, (_, _, source) in zip(jnames, rows):
        if (name not in mimics or source not in jnames) and source not in readers:
            readers.append(source)
    if not readers:
        raise RobotSpecError(f"{path}: every movable joint of the chain is a mimic joint; none takes a reading")
    col = {n: k for k, n in enumerate(readers)}
    A = torch.zeros(len(jnames), len(readers), dtype=dtype)
    b = torch.zeros(len(jnames), dtype=dtype)
    for i, (scale, shift, source) in enumerate(rows):
        A[i, col[source]] = scale
        b[i] = shift
    return Readings(A, b, dtype=dtype), readers


def _mimic_row(path: Path, name: str, jnames: list[str], mimics: dict, movable: dict) -> tuple[float, float, str]:
    """Joint ``name`` as ``scale * reading + shift`` of the joint its mimics end at (itself when it mimics none)."""
    scale, shift, at, seen = 1.0, 0.0, name, [name]
    while at in mimics:
        m = mimics[at]
        mult = 1.0 if getattr(m, "multiplier", None) is None else float(m.multiplier)
        off = 0.0 if getattr(m, "offset", None) is None else float(m.offset)
        if not (math.isfinite(mult) and math.isfinite(off)):
            raise RobotSpecError(f"{path}: joint '{at}': mimic multiplier and offset must be finite numbers")
        shift, scale = shift + scale * off, scale * mult
        src = m.joint
        if src not in movable:
            raise RobotSpecError(
                f"{path}: joint '{at}' mimics joint '{src}', which is not a movable joint of the URDF "
                f"(the chain's: {', '.join(jnames)})"
            )
        if src in seen:
            raise RobotSpecError(f"{path}: the mimic joints {' -> '.join(seen + [src])} form a cycle")
        seen.append(src)
        at = src
    if scale == 0.0:
        raise RobotSpecError(f"{path}: joint '{name}': mimic multiplier 0 makes it a fixed joint; write it fixed")
    if not MIN_RATIO <= abs(scale) <= MAX_RATIO:
        raise RobotSpecError(
            f"{path}: joint '{name}': mimic multiplier {scale:.3g} (composed along its mimics) is outside "
            f"{MIN_RATIO:g} to {MAX_RATIO:g}: the source's reading noise carried through it would swamp the fit"
        )
    return scale, shift, at


def calibrated_flange(spec: str | os.PathLike) -> str | None:
    """The link a URDF that torchcal wrote (a run's ``robot_calibrated.urdf``) fixed its ``probe`` frame to, or
    None for any other description.

    Loaded with the default tip, such a file's chain ends at that run's lever arm (``probe``, its deepest leaf);
    calibrating it again fits the lever arm afresh and writes the ``probe`` frame anew, so the robot to calibrate
    ends at this link (the flange).
    """
    path = resolve_robot_spec(spec)
    if path.suffix != ".urdf":
        return None
    raw = _read_description(path)
    if not _written_by_torchcal(raw):
        return None
    import re

    m = re.search(
        rb'<joint name="probe_joint" type="fixed">\s*<parent link="([^"<>&]+)"/>\s*<child link="probe"/>', raw
    )
    return m.group(1).decode("utf-8") if m else None


def _written_by_torchcal(raw: bytes) -> bool:
    """Whether a URDF is one torchcal wrote (the header comment of :mod:`torchcal.robot.export`: a DH robot's
    generated file or a URDF robot's own file with calibrated origins)."""
    import re

    return re.search(rb"<!--\s*(Generated|Written) by torchcal ", raw[:1000]) is not None


def _urdf_numbers(path: Path, where: str, el, key: str, default: str, bound: float, unit: str) -> None:
    """Refuse ``el``'s attribute ``key`` unless it is three finite numbers within ``bound`` (``el`` None: absent)."""
    if el is None:
        return
    text = el.get(key, default)
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        values = None
    shown = " ".join(text.split())[:80]
    if values is None or len(values) != 3:
        raise RobotSpecError(
            f'{path}: {where}: <{el.tag} {key}="{shown}"> must be three numbers separated by spaces, e.g. "0 0 1"'
        )
    if not all(math.isfinite(v) for v in values):
        raise RobotSpecError(f'{path}: {where}: <{el.tag} {key}="{shown}"> has non-finite values')
    if max(abs(v) for v in values) > bound:
        raise RobotSpecError(
            f'{path}: {where}: <{el.tag} {key}="{shown}"> is beyond {bound:.4g} {unit}; URDF lengths are metres and '
            "angles radians" + (" (a value in degrees?)" if unit == "rad" else "")
        )


def _check_urdf_elements(path: Path, tree) -> None:
    """What the URDF readers take for granted, checked on the XML with the file and joint named: every joint has a
    unique name, a ``<parent link>`` and a ``<child link>`` that are links of the file, a three-component axis and
    an origin of finite numbers within a kilometre; names hold no control characters."""
    _safe_name(path, "robot name", tree.get("name", ""))
    links: set[str] = set()
    for lk in tree.findall("link"):
        name = lk.get("name")
        if not name:
            raise RobotSpecError(f"{path}: a <link> has no name")
        _safe_name(path, "link name", name)
        if name in links:
            raise RobotSpecError(f"{path}: link name {name!r} occurs twice; link names must be unique")
        links.add(name)
    joints: set[str] = set()
    for j in tree.findall("joint"):
        name = j.get("name")
        if not name:
            raise RobotSpecError(f"{path}: a <joint> has no name")
        _safe_name(path, "joint name", name)
        where = f"joint {name!r}"
        if name in joints:
            raise RobotSpecError(f"{path}: joint name {name!r} occurs twice; joint names must be unique")
        joints.add(name)
        for tag in ("parent", "child"):
            el = j.find(tag)
            if el is None or not el.get("link"):
                raise RobotSpecError(
                    f'{path}: {where} has no <{tag} link="..."/>; every joint needs a parent and a child'
                )
            if el.get("link") not in links:
                raise RobotSpecError(f"{path}: {where}: its {tag} link {el.get('link')!r} is not a <link> of the file")
        _urdf_numbers(path, where, j.find("axis"), "xyz", "1 0 0", math.inf, "")
        origin = j.find("origin")
        _urdf_numbers(path, where, origin, "xyz", "0 0 0", MAX_DESCRIPTION_LENGTH, "m")
        _urdf_numbers(path, where, origin, "rpy", "0 0 0", MAX_DESCRIPTION_ANGLE, "rad")


def _parse_lxml(path: Path, raw: bytes):
    """The root element, parsed strictly: yourdfpy falls back to a recovering parser that accepts truncated files
    and trailing junk. No DTD, no entities, no network."""
    from lxml import etree

    parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False, recover=False)
    try:
        tree = etree.fromstring(raw, parser=parser)
    except etree.XMLSyntaxError as e:
        raise RobotSpecError(f"{path}: not well-formed XML: {e}") from None
    if tree.getroottree().docinfo.internalDTD is not None or tree.getroottree().docinfo.doctype:
        raise RobotSpecError(f"{path}: a DOCTYPE/entity declaration is not accepted in a robot description")
    return tree


def _parse_stdlib(path: Path, raw: bytes):
    """The root element by ``xml.etree`` (strict as well); a DOCTYPE or entity declaration is refused before
    parsing, as :func:`_parse_lxml` refuses it."""
    import re
    import xml.etree.ElementTree as ET

    if re.search(rb"<!\s*(DOCTYPE|ENTITY)", raw, flags=re.IGNORECASE):
        raise RobotSpecError(f"{path}: a DOCTYPE/entity declaration is not accepted in a robot description")
    try:
        return ET.fromstring(raw)
    except ET.ParseError as e:
        raise RobotSpecError(f"{path}: not well-formed XML: {e}") from None


def _origin_matrix(el) -> np.ndarray | None:
    """``<origin xyz rpy>`` as a 4x4 matrix, computed as yourdfpy does (``trimesh.transformations.compose_matrix``
    with static ``xyz`` Euler angles: ``T(xyz) @ Rz(y) Ry(p) Rx(r)``, the same operations in the same order)."""
    if el is None:
        return None
    x = np.array([float(v) for v in el.get("xyz", "0 0 0").split()])
    ai, aj, ak = (float(v) for v in el.get("rpy", "0 0 0").split())
    si, sj, sk = np.sin(ai), np.sin(aj), np.sin(ak)
    ci, cj, ck = np.cos(ai), np.cos(aj), np.cos(ak)
    cc, cs, sc, ss = ci * ck, ci * sk, si * ck, si * sk
    R = np.eye(4)
    R[0, 0], R[0, 1], R[0, 2] = cj * ck, sj * sc - cs, sj * cc + ss
    R[1, 0], R[1, 1], R[1, 2] = cj * sk, sj * ss + cc, sj * cs - sc
    R[2, 0], R[2, 1], R[2, 2] = -sj, cj * si, cj * ci
    T = np.identity(4)
    T[:3, 3] = x[:3]
    M = np.dot(np.dot(np.identity(4), T), R)
    M /= M[3, 3]
    return M


def _urdf_elements(path: Path, tree):
    """The parts of a parsed URDF (root element) that :func:`load_urdf` reads, with yourdfpy's attribute names
    and defaults: ``.robot.name``, ``.robot.joints`` (name, type, parent, child, origin, axis, limit, mimic) and
    ``.robot.links`` (name, inertial with mass and origin)."""
    from types import SimpleNamespace as NS

    def num(el, key):
        v = None if el is None else el.get(key)
        return None if v is None else float(v)

    try:
        joints = []
        for j in tree.findall("joint"):
            axis = j.find("axis")
            lim = j.find("limit")
            mimic = j.find("mimic")
            joints.append(
                NS(
                    name=j.attrib["name"],
                    type=j.get("type"),
                    parent=j.find("parent").get("link"),
                    child=j.find("child").get("link"),
                    origin=_origin_matrix(j.find("origin")),
                    axis=np.array([1.0, 0, 0])
                    if axis is None
                    else np.array([float(v) for v in axis.get("xyz", "1 0 0").split()]),
                    limit=None if lim is None else NS(lower=num(lim, "lower"), upper=num(lim, "upper")),
                    mimic=None
                    if mimic is None
                    else NS(
                        joint=mimic.get("joint"),
                        multiplier=float(mimic.get("multiplier", 1.0)),
                        offset=float(mimic.get("offset", 0.0)),
                    ),
                )
            )
        links = []
        for lk in tree.findall("link"):
            ine = lk.find("inertial")
            inertial = None
            if ine is not None:
                mass = ine.find("mass")
                inertial = NS(
                    origin=_origin_matrix(ine.find("origin")),
                    mass=None if mass is None else float(mass.get("value", 0.0)),
                )
            links.append(NS(name=lk.attrib["name"], inertial=inertial))
    except (KeyError, AttributeError, ValueError, IndexError) as e:
        raise RobotSpecError(f"{path}: cannot parse URDF: {type(e).__name__}: {e}") from None
    return NS(robot=NS(name=tree.get("name"), joints=joints, links=links))
