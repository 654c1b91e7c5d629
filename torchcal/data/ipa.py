"""Importer for the ipa-robot-accuracy data set (UR10 + Leica laser tracker with a T-Mac probe).

Landgraf, Ernst, Schleth, Fabritius, Huber, "A Hybrid Neural Network Approach for Increasing
the Absolute Accuracy of Industrial Robots", IEEE CASE 2021 (Fraunhofer IPA; MIT licence).

Only the pose files ``Series_*/measurements_*.csv`` are read: one row per measured pose,
``;``-separated, decimal commas, CRLF line ends, one header row::

    Timestamp;Goal x;...;Goal yaw;shoulder_pan_joint;...;wrist_3_joint;measurement_temperature;
    measurement_x;[measurement_std_x;]measurement_y;...;measurement_rz[;measurement_std_rz]

Units in the file: joints [rad], goals [m, rad] in the ROS ``base_link`` frame (the UR DH base
rotated by pi about z), measured T-Mac position [mm] and intrinsic XYZ Euler angles [deg] in
the tracker frame, standard deviations [mm, deg]. :func:`read_ipa` returns SI units.
"""

from __future__ import annotations

import datetime
import os
import re
from pathlib import Path

import torch

from torchcal.data.measurements import Measurements, _read_text, _wrong_cell_count, write_measurements
from torchcal.errors import MeasurementFileError
from torchcal.robot import transforms as tf
from torchcal.robot.ur_urdf import JOINT_NAMES

__all__ = ["IPA_JOINTS", "convert_ipa", "read_ipa"]

#: Joint columns of the IPA files, base to tip (UR controller names).
IPA_JOINTS = JOINT_NAMES
_GOAL = ("Goal x", "Goal y", "Goal z", "Goal roll", "Goal pitch", "Goal yaw")
_POSITION = ("measurement_x", "measurement_y", "measurement_z")
_EULER = ("measurement_rx", "measurement_ry", "measurement_rz")
_STD = ("measurement_std_x", "measurement_std_y", "measurement_std_z")
_STD_EULER = ("measurement_std_rx", "measurement_std_ry", "measurement_std_rz")
_TEMPERATURE = "measurement_temperature"
_TIMESTAMP = "Timestamp"
_REQUIRED = (*_GOAL, *IPA_JOINTS, _TEMPERATURE, *_POSITION, *_EULER)
_HANDEYE_MARKERS = ("flange_x", "flange_qw")

# A number with '.' or ',' as decimal mark, optional exponent; no nan/inf, no '_', no thousands marks.
_NUMBER_RE = re.compile(r"[+-]?(?:[0-9]+(?:[.,][0-9]*)?|[.,][0-9]+)(?:[eE][+-]?[0-9]+)?")
_INTACT_TIMESTAMP_RE = re.compile(r"[0-9]{14}")
_SERIES_RE = re.compile(r"Series_([A-Za-z0-9]+)")
_MIN_MEDIAN_DISTANCE_MM = 20.0  # closer than a tracker measures: the file is not in mm
_GOAL_DECIMALS = 6  # goals are compared rounded to 1e-6 (m, rad)
_STRIP = " \t\x00"  # Series_D hand-eye lines end in NUL bytes and spaces

META = {
    "source": "ipa-robot-accuracy",
    "robot": "ur10",
    "citation": "Landgraf et al., IEEE CASE 2021",
    "licence": "MIT",
    "frame": "base_link goals are the UR DH base rotated by pi about z",
}


def read_ipa(path: str | os.PathLike) -> Measurements:
    """Read one ``Series_*/measurements_*.csv`` file of the ipa-robot-accuracy data set.

    Args:
        path: the file. ``;`` separator, decimal commas, CRLF or LF, optional UTF-8 BOM; NUL
            bytes and spaces around cells and blank lines are ignored.

    Returns:
        Measurements in SI units, with ``source`` set to ``str(path)`` and ``lines`` the
        1-based file line of each row:

        - ``q`` (N, 6) [rad] from ``shoulder_pan_joint`` ... ``wrist_3_joint``;
        - ``p`` (N, 3) [m] T-Mac position in the tracker frame (``measurement_x/_y/_z`` / 1000);
        - ``temperature`` (N,) [degC] from ``measurement_temperature``;
        - ``sigma`` (N, 3) [m] from ``measurement_std_x/_y/_z`` when present, else None;
          non-positive values are replaced by the median of the positive values of their
          column (count in ``meta['sigma_replaced']``);
        - ``r`` (N, 3) [rad]: the measured T-Mac orientation in the tracker frame as a rotation vector (from the
          intrinsic XYZ Euler angles ``measurement_rx/_ry/_rz``, ``R = Rx(rx) Ry(ry) Rz(rz)``);
        - ``sigma_r`` (N, 3) [rad] from ``measurement_std_rx/_ry/_rz`` when present, else None: the Euler angles'
          standard deviations carried to small rotations about the tracker's axes (:func:`euler_sigma_to_tracker`),
          non-positive values replaced by their column's median as for ``sigma``;
        - ``t`` (N,) [s] since the first row, only when every ``Timestamp`` is an intact
          ``YYYYMMDDhhmmss`` and they are non-decreasing; else None and ``meta['time']`` says why;
        - ``extra``: ``row`` (0-based order in the file), ``goal_id`` (rows with the same
          commanded goal, rounded to 1e-6, share an id; ids in order of first appearance),
          ``tmac_rx/ry/rz`` [rad] the measured T-Mac orientation in the tracker frame as a
          rotation vector (from intrinsic XYZ Euler angles, ``R = Rx(rx) Ry(ry) Rz(rz)``),
          ``goal_x/y/z`` [m] the commanded T-Mac TCP position in ``base_link``, and, when the
          timestamps are intact but out of order, ``timestamp_s`` [s] since the first row;
        - ``meta``: data set, series (from the ``Series_X`` folder), robot, citation, licence, frame.

    Raises:
        MeasurementFileError: an unreadable file, a hand-eye file, a missing or duplicate
            column, a malformed cell (names file, line and column).
    """
    path_str = str(path)
    header, index, rows, lines = _cells(path_str, _read_text(path_str))
    columns = _numeric_columns(path_str, header, index, rows, lines)
    q = columns(IPA_JOINTS)
    p = _positions_m(path_str, columns(_POSITION), lines)
    temperature = columns([_TEMPERATURE])[:, 0]
    meta = dict(META)
    series = _SERIES_RE.fullmatch(Path(path_str).absolute().parent.name)
    if series:
        meta["series"] = series.group(1)
    meta["file"] = Path(path_str).name
    euler = columns(_EULER) * tf.DEG
    extra = _extra(columns(_GOAL))
    r = matrix_to_rotvec(tf.rot_x(euler[:, 0]) @ tf.rot_y(euler[:, 1]) @ tf.rot_z(euler[:, 2]))
    sigma, sigma_r = _sigmas(path_str, index, columns, euler, lines, meta)
    t = _time_column(path_str, index, rows, lines, extra, meta)
    return Measurements(
        q=q,
        p=p,
        t=t,
        temperature=temperature,
        sigma=sigma,
        meta=meta,
        source=path_str,
        lines=tuple(lines),
        extra=extra,
        r=r,
        sigma_r=sigma_r,
    )


def _numeric_columns(path: str, header: list[str], index: dict[str, int], rows: list[list[str]], lines: list[int]):
    """The numeric cells of an IPA file as one float64 table (a malformed cell names its file, line and column);
    returns the function that takes columns out of it by name, ``(N, len(names))``."""
    numeric = [c for c in header if c != _TIMESTAMP]
    table = torch.tensor(
        [[_number(path, row[index[c]], line, c) for c in numeric] for row, line in zip(rows, lines)],
        dtype=torch.float64,
    ).reshape(len(rows), len(numeric))
    col = {c: k for k, c in enumerate(numeric)}

    def columns(names) -> torch.Tensor:
        return table[:, [col[c] for c in names]].clone()

    return columns


def _sigmas(path: str, index: dict, columns, euler: torch.Tensor, lines: list[int], meta: dict):
    """The per-row standard deviations of position [m] and orientation [rad, tracker axes] where the file has
    them (else None), non-positive values replaced by their column's median and counted in ``meta``."""
    sigma = None
    if _STD[0] in index:
        sigma, replaced = _positive_sigma(path, columns(_STD) / 1000.0, lines)
        if replaced:
            meta["sigma_replaced"] = (
                f"{replaced} non-positive measurement_std_x/_y/_z value(s) replaced by their column's median"
            )
    sigma_r = None
    if _STD_EULER[0] in index:
        std, replaced = _positive_sigma(path, columns(_STD_EULER) * tf.DEG, lines, _STD_EULER)
        sigma_r = euler_sigma_to_tracker(euler, std)
        if replaced:
            meta["sigma_r_replaced"] = (
                f"{replaced} non-positive measurement_std_rx/_ry/_rz value(s) replaced by their column's median"
            )
    return sigma, sigma_r


def _time_column(path: str, index: dict, rows: list[list[str]], lines: list[int], extra: dict, meta: dict):
    """``t`` [s] from the ``Timestamp`` column where intact and in order (else None, ``meta['time']`` says why)."""
    if _TIMESTAMP not in index:
        meta["time"] = "no Timestamp column; t left out"
        return None
    t, seconds, note = _times(path, [row[index[_TIMESTAMP]] for row in rows], lines)
    if seconds is not None:
        extra["timestamp_s"] = seconds
    if note:
        meta["time"] = note
    return t


def _cells(path: str, text: str) -> tuple[list[str], dict[str, int], list[list[str]], list[int]]:
    """The header, its column index, the data rows as cells and their 1-based file lines of an IPA file's text."""
    raw_lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    header_index = next((i for i, line in enumerate(raw_lines) if line.strip(_STRIP)), None)
    if header_index is None:
        raise MeasurementFileError(path, "the file is empty; expected the header row of an IPA measurements file")
    header_line = header_index + 1
    header = [c.strip(_STRIP) for c in raw_lines[header_index].rstrip(_STRIP).split(";")]
    index = _check_header(path, header, header_line)
    rows: list[list[str]] = []
    lines: list[int] = []
    for i in range(header_index + 1, len(raw_lines)):
        line = raw_lines[i].strip(_STRIP)
        if not line:
            continue
        cells = [c.strip(_STRIP) for c in line.split(";")]
        if len(cells) != len(header):
            _wrong_cell_count(path, cells, header, i + 1, line, decimal_point_hint=False)
        rows.append(cells)
        lines.append(i + 1)
    if not rows:
        raise MeasurementFileError(path, "the file has a header but no data rows", line=header_line)
    return header, index, rows, lines


def _positions_m(path: str, p_mm: torch.Tensor, lines: list[int]) -> torch.Tensor:
    """The T-Mac positions (N, 3) in metres from the file's millimetres; refuses a file that looks like metres."""
    median_mm = p_mm.norm(dim=1).median().item()
    if median_mm < _MIN_MEDIAN_DISTANCE_MM:
        i = int((p_mm.norm(dim=1) < _MIN_MEDIAN_DISTANCE_MM).nonzero()[0, 0])
        raise MeasurementFileError(
            path,
            f"measured positions look like metres: median distance from the tracker {median_mm:.6g} mm",
            line=lines[i],
            column=_POSITION[int(p_mm[i].abs().argmax())],
            hint="the IPA files give measurement_x/_y/_z in millimetres",
        )
    return p_mm / 1000.0


def euler_sigma_to_tracker(euler: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """Per-axis standard deviations ``(N, 3)`` [rad] of the small rotation ``e`` (``R_true = exp(e) R``, tracker
    axes) that independent errors of intrinsic XYZ Euler angles ``euler (N, 3)`` [rad] with standard deviations
    ``std (N, 3)`` [rad] make: ``e = J d(euler)``, ``J = [x, Rx(a) y, Rx(a) Ry(b) z]`` (the angular velocity of
    ``Rx(a) Ry(b) Rz(c)``), and the square roots of ``diag(J diag(std^2) J^T)`` (the correlations are left out:
    the file gives none either)."""
    n = len(euler)
    eye = torch.eye(3, dtype=euler.dtype).expand(n, 3, 3)
    Rx = tf.rot_x(euler[:, 0])
    J = torch.stack([eye[:, :, 0], Rx[:, :, 1], (Rx @ tf.rot_y(euler[:, 1]))[:, :, 2]], dim=2)
    return ((J.square() @ std.square().unsqueeze(-1)).squeeze(-1)).sqrt()


def _extra(goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """``row``, ``goal_id`` and ``goal_x/y/z`` of :func:`read_ipa` from the commanded goals (N, 6) [m, rad]."""
    extra: dict[str, torch.Tensor] = {"row": torch.arange(len(goal), dtype=torch.float64)}
    extra["goal_id"] = _goal_ids(goal)
    extra.update({f"goal_{a}": goal[:, k].clone() for k, a in enumerate("xyz")})
    return extra


def convert_ipa(src: str | os.PathLike, out: str | os.PathLike, *, written_by: str | None = None) -> Measurements:
    """Read an IPA measurements file and write it at ``out`` in the contract format (SI units).

    The output is written atomically by :func:`~torchcal.data.write_measurements`; nothing is
    written when reading fails. ``written_by``: the first line's ``# written_by:`` value (the command).
    Returns the measurements read.
    """
    m = read_ipa(src)
    write_measurements(out, m, written_by=written_by)
    return m


def matrix_to_rotvec(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector (axis * angle, angle in [0, pi]) of ``R (..., 3, 3)``, accurate at every angle.

    Goes through the unit quaternion (Shepperd's method: the branch with the largest
    diagonal term, so no division by a small number), then ``2 atan2(|v|, w) v / |v|`` with
    ``w >= 0``; unlike the trace/arccos formula it stays accurate near 0 and pi.
    """
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    # 4 q_k^2 for k = w, x, y, z; the largest picks the well-conditioned branch
    candidates = torch.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    branch = candidates.argmax(-1, keepdim=True)
    s = torch.sqrt(candidates.gather(-1, branch).clamp_min(1e-300)).squeeze(-1) * 2.0  # 4 |q_k|
    d21, d02, d10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    s10, s02, s21 = R[..., 1, 0] + R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 2, 1] + R[..., 1, 2]
    quats = torch.stack(
        [
            torch.stack([s * s / 4, d21, d02, d10], -1),
            torch.stack([d21, s * s / 4, s10, s02], -1),
            torch.stack([d02, s10, s * s / 4, s21], -1),
            torch.stack([d10, s02, s21, s * s / 4], -1),
        ],
        -2,
    )  # (..., branch, [w x y z]) each times 4 q_k
    quat = quats.gather(-2, branch[..., None].expand(*branch.shape[:-1], 1, 4)).squeeze(-2) / s[..., None]
    quat = quat / quat.norm(dim=-1, keepdim=True)
    quat = torch.where(quat[..., :1] < 0, -quat, quat)
    w, v = quat[..., 0], quat[..., 1:]
    n = v.norm(dim=-1)
    small = n < 1e-8
    # angle / |v| -> 2 / w as |v| -> 0 (w ~ 1 there)
    scale = torch.where(small, 2.0 / w, 2.0 * torch.atan2(n, w) / torch.where(small, 1.0, n))
    return scale[..., None] * v


# --------------------------------------------------------------------------- helpers


def _check_header(path: str, header: list[str], line: int) -> dict[str, int]:
    if any(marker in header for marker in _HANDEYE_MARKERS):
        raise MeasurementFileError(
            path,
            "this is a hand-eye calibration file (commanded flange pose and measured T-Mac pose, "
            "no joint angles); read_ipa reads only the Series_*/measurements_*.csv pose files",
            line=line,
            hint="use Series_*/measurements_*.csv",
        )
    if len(header) == 1:
        raise MeasurementFileError(
            path,
            "the header has a single column; the IPA files are ';'-separated",
            line=line,
        )
    index: dict[str, int] = {}
    for k, name in enumerate(header):
        if name in index:
            raise MeasurementFileError(
                path,
                f"column name '{name}' appears twice (columns {index[name] + 1} and {k + 1})",
                line=line,
                column=name,
            )
        if not name:
            raise MeasurementFileError(path, f"column {k + 1} of the header has no name", line=line)
        index[name] = k
    missing = [c for c in _REQUIRED if c not in index]
    if missing:
        raise MeasurementFileError(
            path,
            f"missing column(s) {', '.join(repr(c) for c in missing)} of an IPA measurements file",
            line=line,
            column=missing[0],
        )
    for names, what in ((_STD, "x, y and z"), (_STD_EULER, "rx, ry and rz")):
        std = [c for c in names if c in index]
        if std and len(std) != len(names):
            absent = [c for c in names if c not in index]
            raise MeasurementFileError(
                path,
                f"standard deviations must be given for {what} together; missing {', '.join(absent)}",
                line=line,
                column=absent[0],
            )
    return index


def _number(path: str, cell: str, line: int, column: str) -> float:
    if _NUMBER_RE.fullmatch(cell):
        return float(cell.replace(",", "."))
    what = "empty cell; every column needs a value" if not cell else f"{cell!r} is not a number"
    raise MeasurementFileError(
        path,
        what,
        line=line,
        column=column,
        hint="numbers use ',' or '.' as decimal mark, e.g. '0,365141'; no NaN or inf",
    )


def _positive_sigma(path: str, sigma: torch.Tensor, lines: list[int], names=_STD) -> tuple[torch.Tensor, int]:
    bad = sigma <= 0
    if not bad.any():
        return sigma, 0
    for j in range(3):
        good = sigma[~bad[:, j], j]
        if good.numel() == 0:
            raise MeasurementFileError(
                path,
                f"every {names[j]} is <= 0; no positive standard deviation to fall back on",
                line=lines[0],
                column=names[j],
            )
        sigma[bad[:, j], j] = torch.quantile(good, 0.5)  # mean of the middle two for even counts
    return sigma, int(bad.sum())


def _goal_ids(goal: torch.Tensor) -> torch.Tensor:
    # "+ 0.0" folds -0.0 into 0.0 (equal already, but keeps the keys printable alike)
    keys = [tuple(round(v, _GOAL_DECIMALS) + 0.0 for v in row) for row in goal.tolist()]
    ids: dict[tuple[float, ...], int] = {}
    return torch.tensor([ids.setdefault(key, len(ids)) for key in keys], dtype=torch.float64)


def _times(path: str, cells: list[str], lines: list[int]):
    """``(t, timestamp_s, note)``: t only for intact, non-decreasing timestamps."""
    stamps: list[datetime.datetime] = []
    for cell, line in zip(cells, lines):
        if _INTACT_TIMESTAMP_RE.fullmatch(cell):
            try:
                stamps.append(datetime.datetime.strptime(cell, "%Y%m%d%H%M%S"))
                continue
            except ValueError:
                pass
        if not _NUMBER_RE.fullmatch(cell):
            _number(path, cell, line, _TIMESTAMP)
    if len(stamps) != len(cells):
        return None, None, "timestamps destroyed (not YYYYMMDDhhmmss, e.g. Excel's 2,02011E+13); t left out"
    seconds = torch.tensor([(s - stamps[0]).total_seconds() for s in stamps], dtype=torch.float64)
    back = (seconds[1:] < seconds[:-1]).nonzero()
    if back.numel():
        i = int(back[0, 0]) + 1
        count = int(back.numel())
        note = (
            f"timestamps are not non-decreasing ({count} step(s) back, the first at line {lines[i]}); "
            "t left out, the times are in extra timestamp_s"
        )
        return None, seconds, note
    return seconds, None, None
