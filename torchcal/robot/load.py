"""Robot descriptions -> :class:`RobotModel`: built-in names, DH tables in YAML, URDF files."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from torchcal.errors import RobotSpecError
from torchcal.robot.model import DHConvention, DHGeometry, RobotModel, URDFGeometry

#: Where the built-in robot descriptions live; ``TORCHCAL_ROBOTS`` overrides it.
ROBOTS_DIR = Path(os.environ.get("TORCHCAL_ROBOTS", Path(__file__).resolve().parents[2] / "robots"))


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
    if path.is_file():
        raise RobotSpecError(f"{path}: unknown robot description type '{path.suffix}', expected .urdf, .yaml or .yml")
    name = str(spec)
    for candidate in (ROBOTS_DIR / name, ROBOTS_DIR / f"{name}.yaml", ROBOTS_DIR / f"{name}.yml",
                      ROBOTS_DIR / f"{name}.urdf"):
        if candidate.is_file() and candidate.suffix in (".yaml", ".yml", ".urdf"):
            return candidate
    raise RobotSpecError(
        f"robot '{spec}' is neither a file nor a built-in robot; built-ins: {', '.join(builtin_robots()) or 'none'}"
    )


def load_robot(spec: str | os.PathLike, *, base_link: str | None = None, tip_link: str | None = None,
               dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu") -> RobotModel:
    """Load a robot: a built-in name (``ur5``, ``ur10``, ``panda``), a URDF path or a DH YAML path.

    Args:
        spec: built-in name or path.
        base_link, tip_link: URDF only, pick the chain when the tree has several.
        dtype: must be float64 (the calibration path is float64).

    Returns:
        A :class:`RobotModel` with nominal geometry and zero corrections.
    """
    path = resolve_robot_spec(spec)
    if path.suffix == ".urdf":
        return load_urdf(path, base_link=base_link, tip_link=tip_link, dtype=dtype, device=device)
    if base_link or tip_link:
        raise RobotSpecError(f"{path}: --base-link/--tip-link apply to URDF robots only, this is a DH table")
    return load_dh_yaml(path, dtype=dtype, device=device)


# --------------------------------------------------------------------------- DH
def _number(path, where: str, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RobotSpecError(f"{path}: {where}: '{key}' must be a number, got {value!r}")
    if not math.isfinite(value):
        raise RobotSpecError(f"{path}: {where}: '{key}' must be finite, got {value!r}")
    return float(value)


def load_dh_yaml(path: str | os.PathLike, *, dtype=torch.float64, device="cpu") -> RobotModel:
    """Load a DH table (CONTRACT §2): ``name``, ``convention``, ``joints: [{a, alpha, d, theta, ...}]``.

    Optional per joint: ``lower``, ``upper`` [rad] (default +-2 pi), ``mass`` [kg] and ``com``
    [m, in DH frame i] (all joints or none), ``name``.
    """
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as e:
        raise RobotSpecError(f"{path}: not valid YAML: {e}") from None
    except OSError as e:
        raise RobotSpecError(f"{path}: cannot read: {e.strerror}") from None
    if not isinstance(doc, dict) or "joints" not in doc:
        raise RobotSpecError(f"{path}: expected a mapping with 'name', 'convention' and 'joints'")
    conv = str(doc.get("convention", "standard")).lower()
    valid = [c.value for c in DHConvention]
    if conv not in valid:
        raise RobotSpecError(f"{path}: convention '{conv}' is not one of {valid}")
    joints = doc["joints"]
    if not isinstance(joints, list) or not joints:
        raise RobotSpecError(f"{path}: 'joints' must be a non-empty list, base to tip")
    cols = {k: [] for k in ("a", "alpha", "d", "theta", "lower", "upper")}
    masses, coms, names = [], [], []
    for i, j in enumerate(joints):
        where = f"joint {i + 1}"
        if not isinstance(j, dict):
            raise RobotSpecError(f"{path}: {where}: expected a mapping like {{a: .., alpha: .., d: .., theta: ..}}")
        unknown = set(j) - {"a", "alpha", "d", "theta", "lower", "upper", "mass", "com", "name"}
        if unknown:
            raise RobotSpecError(f"{path}: {where}: unknown keys {sorted(unknown)}; valid: a, alpha, d, theta, "
                                 "lower, upper, mass, com, name")
        for key in ("a", "alpha", "d", "theta"):
            if key not in j:
                raise RobotSpecError(f"{path}: {where}: missing '{key}'")
            cols[key].append(_number(path, where, key, j[key]))
        cols["lower"].append(_number(path, where, "lower", j.get("lower", -2 * math.pi)))
        cols["upper"].append(_number(path, where, "upper", j.get("upper", 2 * math.pi)))
        if cols["lower"][-1] >= cols["upper"][-1]:
            raise RobotSpecError(f"{path}: {where}: lower limit {cols['lower'][-1]} is not below upper "
                                 f"{cols['upper'][-1]}")
        if "mass" in j:
            masses.append(_number(path, where, "mass", j["mass"]))
            com = j.get("com", [0.0, 0.0, 0.0])
            if not isinstance(com, list) or len(com) != 3:
                raise RobotSpecError(f"{path}: {where}: 'com' must be a list of 3 numbers [m]")
            coms.append([_number(path, where, "com", c) for c in com])
        names.append(str(j.get("name", f"joint{i + 1}")))
    if masses and len(masses) != len(joints):
        raise RobotSpecError(f"{path}: 'mass' is given for {len(masses)} of {len(joints)} joints; give all or none")
    convention = DHConvention(conv)
    geometry = DHGeometry(a=cols["a"], alpha=cols["alpha"], d=cols["d"], theta=cols["theta"],
                          convention=convention, dtype=dtype, device=device)
    limits = torch.tensor(list(zip(cols["lower"], cols["upper"])), dtype=dtype)
    com_t = None
    if masses:
        # centres of mass are given in DH frame i; the model keeps them in the frame that
        # rotates with joint i (F_i). Standard DH: frame i = F_i @ M_i; modified: frame i = F_i.
        com_t = torch.tensor(coms, dtype=dtype)
        if convention is DHConvention.STANDARD:
            M = geometry.origins()[1:].detach()
            com_t = (M[:, :3, :3] @ com_t.unsqueeze(-1)).squeeze(-1) + M[:, :3, 3]
    dof = len(joints)
    return RobotModel(
        name=str(doc.get("name", path.stem)),
        geometry=geometry,
        limits=limits,
        joint_names=names,
        link_names=["base"] + [f"link{i + 1}" for i in range(dof)] + ["flange"],
        masses=torch.tensor(masses, dtype=dtype) if masses else None,
        coms=com_t,
        source=str(path),
        kind="dh",
        base_link="base",
        tip_link="flange",
        dtype=dtype,
        device=device,
    ).to(device)


# ------------------------------------------------------------------------- URDF
def load_urdf(path: str | os.PathLike, *, base_link: str | None = None, tip_link: str | None = None,
              dtype=torch.float64, device="cpu") -> RobotModel:
    """Load a serial chain from a URDF with yourdfpy, in float64, meshes not loaded.

    The chain runs from ``base_link`` (default: the root) to ``tip_link`` (default: the leaf
    reached through the most movable joints; ambiguous trees must name it). Fixed joints
    are folded into the neighbouring origins; revolute and continuous joints are the
    robot's joints (prismatic joints are not supported yet and raise).
    """
    import yourdfpy

    path = Path(path)
    try:
        urdf = yourdfpy.URDF.load(str(path), load_meshes=False, build_scene_graph=False,
                                  build_collision_scene_graph=False, load_collision_meshes=False)
    except Exception as e:  # yourdfpy raises assorted exception types on malformed files
        raise RobotSpecError(f"{path}: cannot parse URDF: {e}") from None
    joints = urdf.robot.joints
    child_of = {j.child: j for j in joints}
    children: dict[str, list] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)
    links = [lk.name for lk in urdf.robot.links]
    roots = [lk for lk in links if lk not in child_of]
    if base_link is None:
        if len(roots) != 1:
            raise RobotSpecError(f"{path}: the URDF has {len(roots)} root links {roots}; pick one with --base-link")
        base_link = roots[0]
    elif base_link not in links:
        raise RobotSpecError(f"{path}: base link '{base_link}' not found; links: {', '.join(links)}")

    def path_to(link: str) -> list:
        out = []
        while link != base_link:
            if link not in child_of:
                return []
            j = child_of[link]
            out.append(j)
            link = j.parent
        return out[::-1]

    if tip_link is None:
        def n_movable(link):
            return sum(j.type in ("revolute", "continuous", "prismatic") for j in path_to(link))

        leaves = [lk for lk in links if lk not in children and (lk == base_link or path_to(lk))]
        best = max((n_movable(lk) for lk in leaves), default=0)
        cands = [lk for lk in leaves if n_movable(lk) == best]
        if best == 0 or len(cands) != 1:
            raise RobotSpecError(f"{path}: cannot choose the tip link: leaves {cands} each end a chain of {best} "
                                 "joints; pick one with --tip-link")
        tip_link = cands[0]
    elif tip_link not in links:
        raise RobotSpecError(f"{path}: tip link '{tip_link}' not found; links: {', '.join(links)}")
    chain = path_to(tip_link)
    if not chain:
        raise RobotSpecError(f"{path}: tip link '{tip_link}' is not below base link '{base_link}'")

    origins, axes, lims, jnames, lnames = [], [], [], [], [base_link]
    masses, coms = [], []
    pending = np.eye(4)
    for j in chain:
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
        if j.type == "fixed":
            pending = pending @ origin
            continue
        if j.type not in ("revolute", "continuous"):
            raise RobotSpecError(f"{path}: joint '{j.name}' is {j.type}; torchcal supports revolute chains")
        origins.append(pending @ origin)
        pending = np.eye(4)
        axis = np.asarray(j.axis if j.axis is not None else [1.0, 0.0, 0.0], dtype=np.float64)
        axes.append(axis / np.linalg.norm(axis))
        if j.type == "continuous" or j.limit is None or j.limit.lower is None or j.limit.upper is None:
            lims.append((-2 * math.pi, 2 * math.pi))
        else:
            lims.append((float(j.limit.lower), float(j.limit.upper)))
        jnames.append(j.name)
        lnames.append(j.child)
    if not origins:
        raise RobotSpecError(f"{path}: no movable joint between '{base_link}' and '{tip_link}'")
    origins.append(pending)
    lnames.append(tip_link)

    # masses: each moving body is the child link of a joint plus every link fixed to it
    # before the next movable joint (on the chain); centre of mass in the joint's child frame
    link_by_name = {lk.name: lk for lk in urdf.robot.links}
    movable_idx = -1
    body_m = [0.0] * len(jnames)
    body_c = [np.zeros(3) for _ in jnames]
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
    masses, coms = (body_m, body_c) if have_inertia else (None, None)

    geometry = URDFGeometry(origins=torch.tensor(np.stack(origins), dtype=dtype),
                            axes=torch.tensor(np.stack(axes), dtype=dtype), joint_names=jnames, dtype=dtype,
                            device=device)
    return RobotModel(
        name=urdf.robot.name or path.stem,
        geometry=geometry,
        limits=torch.tensor(lims, dtype=dtype),
        joint_names=jnames,
        link_names=lnames,
        masses=None if masses is None else torch.tensor(masses, dtype=dtype),
        coms=None if coms is None else torch.tensor(np.stack(coms), dtype=dtype),
        source=str(path),
        kind="urdf",
        base_link=base_link,
        tip_link=tip_link,
        dtype=dtype,
        device=device,
    ).to(device)
