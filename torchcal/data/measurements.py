"""Measurement files: the CSV format of the contract (section 1), read, validated and written.

A file holds one header row and one row per measured pose::

    # robot: ur5            <- '# key: value' comment lines before the header go to ``meta``
    q1,q2,...,qN,x,y,z[,t][,temperature][,sx,sy,sz][,other numeric columns]

Inside torchcal everything is SI (m, rad, s); millimetres and degrees are converted here,
at the I/O edge, and only when asked for. Every problem raises
:class:`~torchcal.errors.MeasurementFileError` naming the file, the 1-based line as an
editor shows it (comment and header lines count) and the column.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import re
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchcal.data.load import check_load, payload_com_of, payload_of, torques_of
from torchcal.errors import MeasurementFileError, OptionError, ShapeError

__all__ = ["ANGLE_UNITS", "LENGTH_UNITS", "Measurements", "read_measurements", "write_measurements"]

#: Accepted ``length_unit`` values and the divisor that turns them into metres.
LENGTH_UNITS: dict[str, float] = {"m": 1.0, "mm": 1000.0}
#: Accepted ``angle_unit`` values and the factor that turns them into radians.
ANGLE_UNITS: dict[str, float] = {"rad": 1.0, "deg": math.pi / 180.0}

_POSITION = ("x", "y", "z")
_SIGMA = ("sx", "sy", "sz")
#: the measured orientation (a rotation vector, instrument frame) of a 6-D probe and its standard deviations [rad]
_ROTATION = ("rx", "ry", "rz")
_ROTATION_SIGMA = ("srx", "sry", "srz")
#: label columns: integers or names, stored as index tensors with the names in order of first appearance
_LABELS = ("station", "probe")
#: text columns that torchcal writes for the reader and ignores on reading (predict's ``model``: which model gave
#: the row; ``conditions``: whether its load was one the run was fitted at), so that its output reads back as
#: measurements
_IGNORED_TEXT = ("model", "conditions")
_RESERVED = frozenset(_POSITION + _SIGMA + _ROTATION + _ROTATION_SIGMA + ("t", "temperature") + _LABELS)
_JOINT_RE = re.compile(r"q([0-9]+)")
_META_RE = re.compile(r"#\s*([A-Za-z_][A-Za-z0-9_.\-]*)\s*:\s*(.*?)\s*")

# Unit mix-up thresholds (declared unit -> what would be absurd in it).
_MAX_MEDIAN_DISTANCE_M = 50.0  # a laser tracker does not measure a robot from 50 m away
_MIN_MEDIAN_DISTANCE_MM = 20.0  # ... nor from 2 cm
_MAX_MEDIAN_SIGMA_M = 0.01  # a 1 cm standard deviation is not a tracker measurement
_MAX_ABS_ANGLE_RAD = 2.0 * math.pi + 1e-9
_JOINT_LIMIT_TOL = 1e-12
#: Largest position or standard deviation a file may hold [m]: no tracker measures 1000 km
MAX_POSITION_M = 1e6
#: Temperatures a file may hold [degC]: beyond them a robot is not calibrated (or the unit is Kelvin/Fahrenheit)
TEMPERATURE_RANGE_C = (-100.0, 200.0)
_MIN_DEGREES_MOVED = 1.0  # deg: below it a degree file near zero (a home pose) could be either unit


def _check_option(name: str, value: str, valid: Mapping[str, float]) -> None:
    if value not in valid:
        choices = ", ".join(repr(v) for v in valid)
        raise OptionError(f"{name} must be one of {choices}, got {value!r}")


@dataclass(frozen=True, eq=False)
class Measurements:
    """A measurement set in SI units, one row per pose.

    Attributes:
        q: (N, dof) float64 joint readings [rad].
        p: (N, 3) float64 probe positions in the tracker frame [m], or None when absent.
        t: (N,) float64 acquisition times [s], or None.
        temperature: (N,) float64 temperatures [degC], or None.
        sigma: (N, 3) float64 per-point standard deviations (sx, sy, sz) [m], or None.
        meta: metadata from the file's ``# key: value`` comment lines.
        source: the path the set was read from, or None.
        lines: 1-based file line of each row, for error messages downstream.
        extra: other numeric columns, (N,) float64 each, in file order; the load columns (``payload``,
            ``payload_x..z`` [m], ``tau1..tauN``) among them, read through :attr:`payload`, :attr:`payload_com` and
            :attr:`tau` (:mod:`torchcal.data.load`).
        r: (N, 3) float64 measured orientation of the probe frame in the tracker frame as a rotation vector [rad]
            (a 6-D probe such as a T-Mac: columns rx, ry, rz), or None.
        sigma_r: (N, 3) float64 standard deviations of the orientation [rad] (srx, sry, srz): of a small rotation
            of the measured frame about the tracker's x, y, z axes (``R_true = exp(e) R_measured``), or None.
        station: (N,) int64 index into ``station_names`` of the instrument placement that measured each row, or None
            (one placement).
        station_names: the stations' names (the file's text), in order of first appearance.
        probe: (N,) int64 index into ``probe_names`` of the reflector each row measured, or None (one probe).
        probe_names: the probes' names, in order of first appearance.
        orientation_used: (N,) bool, the rows whose orientation ``r`` a fit uses, or None (every row's). A row whose
            orientation is a gross error but whose position is sound keeps its position this way
            (:meth:`drop_orientation`); never read from a file.
    """

    q: torch.Tensor
    p: torch.Tensor | None = None
    t: torch.Tensor | None = None
    temperature: torch.Tensor | None = None
    sigma: torch.Tensor | None = None
    meta: dict[str, str] = field(default_factory=dict)
    source: str | None = None
    lines: tuple[int, ...] = ()
    extra: dict[str, torch.Tensor] = field(default_factory=dict)
    r: torch.Tensor | None = None
    sigma_r: torch.Tensor | None = None
    station: torch.Tensor | None = None
    station_names: tuple[str, ...] = ()
    probe: torch.Tensor | None = None
    probe_names: tuple[str, ...] = ()
    orientation_used: torch.Tensor | None = None

    def __post_init__(self) -> None:
        q = self.q
        if not isinstance(q, torch.Tensor) or q.dim() != 2 or q.dtype != torch.float64:
            raise ShapeError(f"q must be a float64 tensor of shape (N, dof), got {_describe(q)}")
        n = q.shape[0]
        for name, value, shape in (
            ("p", self.p, (n, 3)),
            ("t", self.t, (n,)),
            ("temperature", self.temperature, (n,)),
            ("sigma", self.sigma, (n, 3)),
            ("r", self.r, (n, 3)),
            ("sigma_r", self.sigma_r, (n, 3)),
            *((f"extra[{k!r}]", v, (n,)) for k, v in self.extra.items()),
        ):
            if value is None and not name.startswith("extra"):
                continue
            ok = isinstance(value, torch.Tensor) and tuple(value.shape) == shape
            if not ok or value.dtype != torch.float64:
                raise ShapeError(
                    f"{name} must be a float64 tensor of shape {_shape_text(shape)} to match "
                    f"q {_describe(q)}, got {_describe(value)}"
                )
            if value.device != q.device:
                raise ShapeError(f"{name} is on {value.device} but q is on {q.device}")
        if self.sigma_r is not None and self.r is None:
            raise ShapeError("sigma_r (orientation standard deviations) needs r (the measured orientation)")
        _check_orientation_used(self.orientation_used, self.r, q)
        for name in _LABELS:
            _check_label(name, getattr(self, name), getattr(self, f"{name}_names"), q)
        if len(self.lines) not in (0, n):
            raise ShapeError(f"lines must hold one line number per row ({n}), got {len(self.lines)}")
        if not self.lines:
            object.__setattr__(self, "lines", tuple(range(2, n + 2)))
        for key in self.extra:
            if not _valid_extra_name(key):
                raise ShapeError(
                    f"extra column name {key!r} is not allowed: it must be non-empty, must not be a "
                    "standard column (q1.., x, y, z, t, temperature, sx, sy, sz, rx, ry, rz, srx, sry, srz) "
                    "and must not contain ',', quotes, '#' at its start or line breaks"
                )

    @property
    def n(self) -> int:
        """Number of rows (poses)."""
        return self.q.shape[0]

    @property
    def dof(self) -> int:
        """Number of joints."""
        return self.q.shape[1]

    def subset(self, index: torch.Tensor | slice | Sequence[int]) -> Measurements:
        """Rows picked by ``index`` (LongTensor, bool mask, slice or list of ints), in that order."""
        if isinstance(index, slice):
            lines = self.lines[index]
        else:
            index = torch.as_tensor(index, device=self.q.device)
            if index.dtype == torch.bool:
                if tuple(index.shape) != (self.n,):
                    raise ShapeError(f"a bool index must have shape ({self.n},), got {tuple(index.shape)}")
                index = index.nonzero().squeeze(1)
            elif index.dtype != torch.int64 or index.dim() != 1:
                raise ShapeError(f"index must be a 1-D LongTensor, bool mask or slice, got {_describe(index)}")
            lines = tuple(self.lines[i] for i in index.tolist())

        def pick(x: torch.Tensor | None) -> torch.Tensor | None:
            return None if x is None else x[index]

        return dataclasses.replace(
            self,
            q=self.q[index],
            p=pick(self.p),
            t=pick(self.t),
            temperature=pick(self.temperature),
            sigma=pick(self.sigma),
            meta=dict(self.meta),
            lines=lines,
            extra={k: v[index] for k, v in self.extra.items()},
            r=pick(self.r),
            sigma_r=pick(self.sigma_r),
            station=pick(self.station),
            probe=pick(self.probe),
            orientation_used=pick(self.orientation_used),
        )

    @property
    def payload(self) -> torch.Tensor | None:
        """Each row's payload ``(N,)`` [kg] (the ``payload`` column), or None: no load column (0 kg)."""
        return payload_of(self.extra)

    @property
    def payload_com(self) -> torch.Tensor | None:
        """Each row's payload centre of mass in the flange frame ``(N, 3)`` [m], or None (at the probe)."""
        return payload_com_of(self.extra)

    @property
    def tau(self) -> torch.Tensor | None:
        """Each row's measured joint torques ``(N, dof)`` [N m, N for a prismatic joint], or None."""
        return torques_of(self.extra)

    @property
    def n_stations(self) -> int:
        """Number of instrument placements (1 without a ``station`` column)."""
        return max(1, len(self.station_names))

    @property
    def n_probes(self) -> int:
        """Number of probes (1 without a ``probe`` column)."""
        return max(1, len(self.probe_names))

    def to(self, device: torch.device | str) -> Measurements:
        """The same rows with every tensor on ``device`` (float64 kept; tensors already there are not copied)."""

        def move(x: torch.Tensor | None) -> torch.Tensor | None:
            return None if x is None else x.to(device)

        return dataclasses.replace(
            self,
            q=self.q.to(device),
            p=move(self.p),
            t=move(self.t),
            temperature=move(self.temperature),
            sigma=move(self.sigma),
            meta=dict(self.meta),
            extra={k: v.to(device) for k, v in self.extra.items()},
            r=move(self.r),
            sigma_r=move(self.sigma_r),
            station=move(self.station),
            probe=move(self.probe),
            orientation_used=move(self.orientation_used),
        )

    def with_positions(self, p: torch.Tensor | None) -> Measurements:
        """The same rows with positions ``p`` ((N, 3) float64 [m], or None to drop them)."""
        return dataclasses.replace(self, p=p, meta=dict(self.meta), extra=dict(self.extra))

    def without_orientation(self) -> Measurements:
        """The same rows without the measured orientation (``r``, ``sigma_r`` dropped): a position-only set."""
        return dataclasses.replace(
            self, r=None, sigma_r=None, orientation_used=None, meta=dict(self.meta), extra=dict(self.extra)
        )

    @property
    def orientation_rows(self) -> torch.Tensor | None:
        """Indices ``(M,)`` of the rows whose orientation a fit uses (every row's unless some were dropped), or None
        without orientations."""
        if self.r is None:
            return None
        if self.orientation_used is None:
            return torch.arange(self.n, device=self.q.device)
        return self.orientation_used.nonzero().squeeze(1)

    @property
    def all_orientations_used(self) -> bool:
        """Whether every row's orientation is used (True also without orientations)."""
        return self.orientation_used is None or bool(self.orientation_used.all())

    def drop_orientation(self, rows: torch.Tensor) -> Measurements:
        """The same rows with the orientation of ``rows`` (indices or a bool mask ``(N,)``) no longer used: their
        positions stay, a fit reads their orientation as not measured."""
        if self.r is None:
            raise ShapeError("drop_orientation needs r (the measured orientation)")
        used = self.orientation_used
        used = torch.ones(self.n, dtype=torch.bool, device=self.q.device) if used is None else used.clone()
        used[torch.as_tensor(rows, device=self.q.device)] = False
        return dataclasses.replace(self, orientation_used=used, meta=dict(self.meta), extra=dict(self.extra))


def _check_orientation_used(used: torch.Tensor | None, r: torch.Tensor | None, q: torch.Tensor) -> None:
    """``orientation_used``: a bool ``(N,)`` on q's device, only with ``r``."""
    if used is None:
        return
    if r is None:
        raise ShapeError("orientation_used needs r (the measured orientation)")
    if not isinstance(used, torch.Tensor) or used.dtype != torch.bool or tuple(used.shape) != (q.shape[0],):
        raise ShapeError(f"orientation_used must be a bool tensor of shape ({q.shape[0]},), got {_describe(used)}")
    if used.device != q.device:
        raise ShapeError(f"orientation_used is on {used.device} but q is on {q.device}")


def _check_label(name: str, index: torch.Tensor | None, names: tuple[str, ...], q: torch.Tensor) -> None:
    """A label column: an int64 ``(N,)`` index into ``names`` (non-empty, distinct, writable as one CSV cell)."""
    if index is None:
        if names:
            raise ShapeError(f"{name}_names given without a {name} index")
        return
    if not isinstance(index, torch.Tensor) or index.dtype != torch.int64 or tuple(index.shape) != (q.shape[0],):
        raise ShapeError(f"{name} must be an int64 tensor of shape ({q.shape[0]},), got {_describe(index)}")
    if index.device != q.device:
        raise ShapeError(f"{name} is on {index.device} but q is on {q.device}")
    if len(set(names)) != len(names) or not all(_valid_label(v) for v in names):
        raise ShapeError(
            f"{name}_names must be distinct non-empty names without ',', quotes or line breaks, got {names}"
        )
    if index.numel() and (int(index.min()) < 0 or int(index.max()) >= len(names)):
        raise ShapeError(f"{name} indices must lie in 0..{len(names) - 1} ({name}_names {names})")


def _valid_label(v: object) -> bool:
    return isinstance(v, str) and v == v.strip() and v != "" and not any(c in v for c in ",\"'\r\n")


def labels_of(values: Sequence[object]) -> tuple[torch.Tensor, tuple[str, ...]]:
    """Index tensor ``(N,)`` int64 and names in order of first appearance of a station or probe column's values."""
    names: dict[str, int] = {}
    idx = [names.setdefault(str(v), len(names)) for v in values]
    return torch.tensor(idx, dtype=torch.int64), tuple(names)


def _check_numeric_labels(path: str, column: str, values: Sequence[object], lines: Sequence[int]) -> None:
    """Refuse two labels of one column that are different text but the same number (``1`` and ``1.0``, ``01``): a
    label is a name, so they would silently become two stations (probes); which the user meant cannot be told."""
    seen: dict[float, str] = {}
    for v, line in zip(values, lines):
        text = str(v)
        try:
            number = float(text)
        except ValueError:
            continue
        if not math.isfinite(number):
            continue
        first = seen.setdefault(number, text)
        if first != text:
            raise MeasurementFileError(
                path,
                f"{column} label {text!r} is the number of an earlier label {first!r} written differently; labels are "
                f"names, so these would be two {column}s",
                line=line,
                column=column,
                hint=f"write each {column}'s label the same way on every row",
            )


def _describe(x: object) -> str:
    if isinstance(x, torch.Tensor):
        return f"{x.dtype} tensor of shape {tuple(x.shape)}"
    return type(x).__name__


def _shape_text(shape: tuple[int, ...]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def _valid_extra_name(name: str) -> bool:
    return (
        isinstance(name, str)
        and name == name.strip()
        and name != ""
        and name not in _RESERVED
        and not _JOINT_RE.fullmatch(name)
        and not name.startswith("#")
        and not any(c in name for c in ",\"'\r\n")
    )


# --------------------------------------------------------------------------- reading


def read_measurements(
    path: str | os.PathLike,
    *,
    dof: int | None = None,
    joint_limits: torch.Tensor | None = None,
    length_unit: str = "m",
    angle_unit: str = "rad",
    require_positions: bool = True,
    min_poses: int = 1,
    robot_name: str | None = None,
    purpose: str | None = None,
    require_joints: bool = True,
    joint_types: Sequence[str] | None = None,
    text_columns: bool = False,
) -> Measurements:
    """Read and validate a measurement file; return it in SI units.

    Args:
        path: the CSV file (UTF-8, optional BOM, LF or CRLF line ends).
        dof: number of joints the robot has; the file must have exactly ``q1..q<dof>``.
        joint_limits: (dof, 2) float64 [lower, upper] per joint [rad, m]; readings outside
            (beyond a 1e-12 tolerance) are errors.
        length_unit: ``"m"`` or ``"mm"``, the unit of x, y, z, sx, sy, sz and of the prismatic joints' readings.
        angle_unit: ``"rad"`` or ``"deg"``, the unit of the revolute joints' readings.
        require_positions: whether x, y, z must be present (fitting) or may be absent (predict).
        min_poses: fewer rows than this is an error.
        robot_name: named in messages about the joint count and limits.
        purpose: what the poses are needed for, named in the too-few-poses message.
        require_joints: whether q1..qN must be present; False lets a file of x, y, z alone through
            (compensation targets), with ``q`` of shape (N, 0).
        joint_types: ``"revolute"`` or ``"prismatic"`` per joint (default all revolute): a prismatic joint's
            reading is a length, in ``length_unit``, and its limits are metres.
        text_columns: whether a column of the file's own (not of the format) that holds text is ignored (True:
            predict's input, where notes beside the numbers change nothing) rather than refused.

    Returns:
        The measurements, with ``source`` set to ``str(path)``.

    Raises:
        MeasurementFileError: anything wrong with the file (names file, line and column).
        OptionError: an unknown unit.
        ShapeError: ``joint_limits`` of the wrong shape or dtype.
    """
    joint_limits = _check_arguments(length_unit, angle_unit, dof, joint_limits)
    path_str = str(path)
    meta, layout, table, lines, labels = _read_table(
        path_str, dof, joint_limits, robot_name, require_positions, require_joints, text_columns
    )
    c = _table_columns(table, layout)
    station, station_names, probe, probe_names = _label_columns(path_str, labels, lines)
    _check_columns(path_str, c, lines, layout, length_unit)
    n = len(lines)
    if n < min_poses:
        for_what = f" for {purpose}" if purpose else ""
        raise MeasurementFileError(path_str, f"file has {n} poses, at least {min_poses} are needed{for_what}")
    linear = _linear_readings(c["q"], joint_types)
    _check_units(path_str, c["q"], c["p"], c["sigma"], lines, layout, length_unit, angle_unit, joint_limits, linear)
    q, p, sigma = _to_si(c["q"], c["p"], c["sigma"], linear, length_unit, angle_unit)
    _check_ranges(path_str, p, sigma, c["temperature"], lines, layout, length_unit)
    c["extra"] = check_load(path_str, c["extra"], lines, layout.header_line, len(layout.joints), length_unit)
    if joint_limits is not None and n and layout.joints:
        _check_joint_limits(path_str, q, lines, layout, joint_limits, angle_unit, robot_name, linear, length_unit)

    return Measurements(
        q=q,
        p=p,
        t=c["t"],
        temperature=c["temperature"],
        sigma=sigma,
        meta=meta,
        source=path_str,
        lines=tuple(lines),
        extra=c["extra"],
        r=c["r"],
        sigma_r=c["sigma_r"],
        station=station,
        station_names=station_names,
        probe=probe,
        probe_names=probe_names,
    )


def _read_table(
    path_str: str, dof, joint_limits, robot_name, require_positions: bool, require_joints: bool, text_ok: bool = False
):
    """The file's ``# key: value`` lines, its column layout, its values as an (N, columns) table, each row's line
    number and the label columns' cells; the header checked against the robot's joint count."""
    text = _read_text(path_str)
    # Editors count '\n', '\r\n' and a lone '\r' as one line break each.
    raw_lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    meta, header_index = _comments_and_header(path_str, text, raw_lines)

    header_line = header_index + 1
    header = _parse_header(path_str, raw_lines[header_index], header_line)
    layout = _Layout.from_header(path_str, header, header_line, require_positions, require_joints)
    layout.header_line = header_line
    if layout.joints or require_joints:
        _check_joint_count(path_str, layout, header_line, dof, joint_limits, robot_name)

    text = [n for n in layout.extra if n not in ("model",)] if text_ok else []
    text = _text_columns(raw_lines[header_index + 1 :], header, text)
    values, lines, labels = _parse_rows(path_str, raw_lines, header_index + 1, header, text)
    layout.extra = [n for n in layout.extra if n not in text]
    table = torch.tensor(values, dtype=torch.float64).reshape(len(lines), len(header))
    return meta, layout, table, lines, labels


def _table_columns(table: torch.Tensor, layout: _Layout) -> dict:
    """The table's columns by quantity, in the file's units: ``q``, ``p``, ``t``, ``temperature``, ``sigma``, ``r``,
    ``sigma_r`` (None where the file has none) and ``extra`` (name -> column)."""

    def column(name: str) -> torch.Tensor:
        return table[:, layout.index[name]].clone()

    def columns(names: Sequence[str]) -> torch.Tensor:
        return table[:, [layout.index[c] for c in names]].clone()

    return {
        "q": columns(layout.joints),
        "p": columns(_POSITION) if layout.has_positions else None,
        "t": column("t") if "t" in layout.index else None,
        "temperature": column("temperature") if "temperature" in layout.index else None,
        "sigma": columns(_SIGMA) if layout.has_sigma else None,
        "r": columns(_ROTATION) if layout.has_rotation else None,
        "sigma_r": columns(_ROTATION_SIGMA) if layout.has_rotation_sigma else None,
        "extra": {name: column(name) for name in layout.extra},
    }


def _label_columns(path_str: str, labels: dict, lines) -> tuple:
    """Each row's station and probe as an index into their names (None and () where the file has no such column)."""
    for name, values in labels.items():
        _check_numeric_labels(path_str, name, values, lines)
    station, station_names = labels_of(labels["station"]) if "station" in labels else (None, ())
    probe, probe_names = labels_of(labels["probe"]) if "probe" in labels else (None, ())
    return station, station_names, probe, probe_names


def _linear_readings(q: torch.Tensor, joint_types) -> torch.Tensor:
    """Which readings are lengths (prismatic joints): the length unit applies to them, the angle unit does not."""
    linear = torch.zeros(q.shape[1], dtype=torch.bool)
    if joint_types is not None and q.shape[1]:
        linear = torch.tensor([k == "prismatic" for k in joint_types], dtype=torch.bool)
    return linear


def _check_columns(path_str: str, c: dict, lines, layout: _Layout, length_unit: str) -> None:
    """Times increase, standard deviations are positive, rotation vectors are rotations."""
    if c["t"] is not None:
        _check_monotonic(path_str, c["t"], lines)
    if c["sigma"] is not None:
        _check_positive_sigma(path_str, c["sigma"], lines, layout, length_unit)
    if c["sigma_r"] is not None:
        _check_positive_sigma(path_str, c["sigma_r"], lines, layout, "rad", _ROTATION_SIGMA)
    if c["r"] is not None:
        _check_rotation(path_str, c["r"], lines, layout)


def _to_si(q: torch.Tensor, p, sigma, linear: torch.Tensor, length_unit: str, angle_unit: str):
    """Readings, positions and their standard deviations in m and rad (``linear``: the readings that are lengths)."""
    divisor = LENGTH_UNITS[length_unit]
    if divisor != 1.0:
        # Division (not multiplication by 1e-3) keeps e.g. 1234.5 mm -> 1.2345 m correctly rounded.
        p = None if p is None else p / divisor
        sigma = None if sigma is None else sigma / divisor
        q = torch.where(linear, q / divisor, q)
    if angle_unit != "rad":
        q = torch.where(linear, q, q * ANGLE_UNITS[angle_unit])
    return q, p, sigma


def _check_arguments(length_unit: str, angle_unit: str, dof: int | None, joint_limits) -> torch.Tensor | None:
    """Check :func:`read_measurements`' options; return ``joint_limits`` as a (dof, 2) float64 tensor (or None)."""
    _check_option("length_unit", length_unit, LENGTH_UNITS)
    _check_option("angle_unit", angle_unit, ANGLE_UNITS)
    if dof is not None and (not isinstance(dof, int) or dof < 1):
        raise OptionError(f"dof must be a positive int, got {dof!r}")
    if joint_limits is None:
        return None
    if isinstance(joint_limits, torch.Tensor) and joint_limits.dtype != torch.float64:
        raise ShapeError(f"joint_limits must be float64, got {joint_limits.dtype}")
    joint_limits = torch.as_tensor(joint_limits, dtype=torch.float64)
    if joint_limits.dim() != 2 or joint_limits.shape[1] != 2 or (dof is not None and joint_limits.shape[0] != dof):
        want = f"({dof}, 2)" if dof is not None else "(dof, 2)"
        raise ShapeError(f"joint_limits must have shape {want}, got {tuple(joint_limits.shape)}")
    return joint_limits


def _comments_and_header(path: str, text: str, raw_lines: list[str]) -> tuple[dict[str, str], int]:
    """The ``# key: value`` metadata above the header and the header's 0-based index in ``raw_lines``."""
    meta: dict[str, str] = {}
    for i, line in enumerate(raw_lines):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            match = _META_RE.fullmatch(stripped)
            if match:
                meta[match.group(1)] = match.group(2)
            continue
        return meta, i
    what = "is empty" if not text.strip() else "has only comments"
    raise MeasurementFileError(path, f"the file {what}; expected a header row such as 'q1,...,q6,x,y,z'")


def _check_units(path, q, p, sigma, lines, layout, length_unit, angle_unit, joint_limits, linear) -> None:
    """Refuse values that look like another unit than the one declared (in the file's units, before conversion).

    Unit mix-ups are checked before the joint limits: they explain limit violations and absurd positions better.
    """
    if not lines:
        return
    if p is not None:
        _check_length_unit(path, p, lines, layout, length_unit)
    if sigma is not None and length_unit == "m":
        _check_sigma_unit(path, sigma, lines, layout)
    # the angle checks read the revolute joints alone: a prismatic joint's reading is a length
    q_angles = q.masked_fill(linear, 0.0)
    if angle_unit == "rad" and q.shape[1]:
        _check_angle_unit(path, q_angles, lines, layout, joint_limits)
    if angle_unit == "deg" and q.shape[1]:
        angle_limits = None if joint_limits is None else joint_limits.masked_fill(linear[:, None], 0.0)
        _check_degrees_are_not_radians(path, q_angles, lines, layout, angle_limits)


def _read_text(path: str) -> str:
    from torchcal._inputs import read_bounded

    raw = read_bounded(path, "measurement file", lambda message: MeasurementFileError(path, message))
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = raw.count(b"\n", 0, err.start) + 1
        raise MeasurementFileError(
            path,
            f"the file is not UTF-8 text (byte 0x{raw[err.start]:02x} at offset {err.start})",
            line=line,
            hint="save the file as UTF-8",
        ) from err


def _parse_header(path: str, line: str, line_no: int) -> list[str]:
    try:
        cells = next(csv.reader([line]))
    except csv.Error as err:
        raise MeasurementFileError(path, f"the header row cannot be read as CSV: {err}", line=line_no) from None
    header = [c.strip() for c in cells]
    if len(header) == 1 and (";" in line or "\t" in line):
        raise MeasurementFileError(
            path,
            "the header has a single column; values must be separated by ','",
            line=line_no,
            hint="the file looks ';'- or tab-separated; save it as comma-separated",
        )
    seen: dict[str, int] = {}
    for k, name in enumerate(header, start=1):
        if not name:
            trailing = k == len(header)
            raise MeasurementFileError(
                path,
                f"column {k} of the header has no name",
                line=line_no,
                hint="a trailing ',' at the end of the header adds an empty column" if trailing else None,
            )
        if name in seen:
            raise MeasurementFileError(
                path,
                f"duplicate column name (columns {seen[name]} and {k} are both '{name}')",
                line=line_no,
                column=name,
            )
        seen[name] = k
    return header


@dataclass
class _Layout:
    """Where each known column sits in the header."""

    index: dict[str, int]
    joints: list[str]
    has_positions: bool
    has_sigma: bool
    extra: list[str]
    has_rotation: bool = False
    has_rotation_sigma: bool = False
    header_line: int = 1

    @classmethod
    def from_header(
        cls, path: str, header: list[str], line: int, require_positions: bool, require_joints: bool = True
    ) -> _Layout:
        index = {name: k for k, name in enumerate(header)}
        numbers = {}
        for name in header:
            match = _JOINT_RE.fullmatch(name)
            if not match:
                continue
            digits = match.group(1)
            if digits.startswith("0"):
                raise MeasurementFileError(
                    path,
                    f"joint columns are named q1, q2, ... without leading zeros, got '{name}'",
                    line=line,
                    column=name,
                )
            numbers[int(digits)] = name
        if not numbers and not require_joints:  # x, y alone: name the missing z rather than q1
            _all_or_none(path, header, line, _POSITION, "probe positions")
        if not numbers and (require_joints or not all(c in header for c in _POSITION)):
            why = "joint readings q1..qN are required" if require_joints else "give x, y, z or q1..qN (or both)"
            _missing(path, header, line, ["q1"], why)
        for k in range(1, max(numbers, default=0) + 1):
            if k not in numbers:
                present = ", ".join(numbers[j] for j in sorted(numbers))
                _missing(path, header, line, [f"q{k}"], f"joint columns must run q1..qN without gaps (found {present})")
        joints = [numbers[k] for k in range(1, len(numbers) + 1)]

        has_positions = _all_or_none(path, header, line, _POSITION, "probe positions")
        if require_positions and not has_positions:
            _missing(path, header, line, list(_POSITION), "probe positions x, y, z are required here")
        has_sigma = _all_or_none(path, header, line, _SIGMA, "standard deviations")
        has_rotation = _all_or_none(path, header, line, _ROTATION, "orientations")
        has_rotation_sigma = _all_or_none(path, header, line, _ROTATION_SIGMA, "orientation standard deviations")
        if has_rotation_sigma and not has_rotation:
            _missing(path, header, line, list(_ROTATION), "srx, sry, srz are the standard deviations of rx, ry, rz")
        extra = [n for n in header if n not in _RESERVED and n not in _IGNORED_TEXT and n not in numbers.values()]
        return cls(index, joints, has_positions, has_sigma, extra, has_rotation, has_rotation_sigma)


def _all_or_none(path: str, header: list[str], line: int, names: Sequence[str], what: str) -> bool:
    present = [n for n in names if n in header]
    if present and len(present) != len(names):
        missing = [n for n in names if n not in header]
        _missing(path, header, line, missing, f"{what} need all of {', '.join(names)} (found {', '.join(present)})")
    return bool(present)


def _missing(path: str, header: list[str], line: int, missing: list[str], why: str) -> None:
    names = ", ".join(f"'{m}'" for m in missing)
    lower = {h.lower(): h for h in header}
    near = [f"'{lower[m.lower()]}'" for m in missing if m.lower() in lower]
    hint = f"column names are case-sensitive; found {', '.join(near)}" if near else None
    raise MeasurementFileError(
        path,
        f"missing column{'s' if len(missing) > 1 else ''} {names}: {why}",
        line=line,
        column=missing[0],
        hint=hint,
    )


def _check_joint_count(path, layout: _Layout, line: int, dof, joint_limits, robot_name) -> None:
    n = len(layout.joints)
    if dof is not None:
        expected = dof
        who = f"robot '{robot_name}' has {dof} joints" if robot_name else f"{dof} joints are expected"
    elif joint_limits is not None:
        expected = joint_limits.shape[0]
        who = f"the joint limits cover {expected} joints"
    else:
        return
    if n != expected:
        columns = "q1" if n == 1 else f"q1..q{n}"
        raise MeasurementFileError(
            path,
            f"file has {n} joint column{'s' if n != 1 else ''} ({columns}) but {who}",
            line=line,
            column=f"q{min(n, expected) + 1}",
        )


def _text_columns(data_lines: list[str], header: list[str], candidates: list[str]) -> list[str]:
    """Those of ``candidates`` (extra columns) with a cell that is text in any row: not empty, not an ASCII number.
    A load column (``payload``, ``tau1``..) is never text: predict honours it, and a text cell there is an error."""
    candidates = [n for n in candidates if not re.fullmatch(r"payload|tau[0-9]+", n)]
    if not candidates:
        return []
    index = {header.index(n): n for n in candidates}
    found: set[str] = set()
    for row in csv.reader([ln for ln in data_lines if ln and not ln.isspace() and not ln.lstrip().startswith("#")]):
        for k, name in index.items():
            if _is_text(row[k].strip() if k < len(row) else ""):
                found.add(name)
    return [n for n in candidates if n in found]


def _is_text(cell: str) -> bool:
    """A cell that is no number at all (an empty cell or 'nan' is left to the reader's own refusals)."""
    if not cell:
        return False
    if "_" in cell or not cell.isascii():
        return True
    try:
        float(cell)
    except ValueError:
        return True
    return False


def _parse_rows(path: str, raw_lines: list[str], start: int, header: list[str], text: Sequence[str] = ()):
    """Parse every data row after the header; return (row-major values, line numbers, label column -> cells).

    A label column (``station``, ``probe``) holds integers or names: its cells are kept as text (stripped) and
    stand as 0.0 in the values."""
    ncol = len(header)
    label_cols = {name: header.index(name) for name in _LABELS if name in header}
    labels: dict[str, list[str]] = {name: [] for name in label_cols}
    ignored = [header.index(name) for name in (*_IGNORED_TEXT, *text) if name in header]
    data_lines = []
    line_numbers = []
    for i in range(start, len(raw_lines)):
        line = raw_lines[i]
        if line and not line.isspace():
            data_lines.append(line)
            line_numbers.append(i + 1)

    values: list[float] = []
    rows: list[int] = []
    reader = csv.reader(data_lines, strict=True)
    consumed = 0
    while True:
        try:
            row = next(reader)
        except StopIteration:
            break
        except csv.Error as err:
            # a cell beyond csv's field size limit, or a quote still open at the end of the file
            index = min(consumed, len(line_numbers) - 1)
            why = "unterminated quote in this row" if "end of data" in str(err) else f"not readable as CSV: {err}"
            raise MeasurementFileError(path, why, line=line_numbers[index]) from None
        index = consumed
        consumed = reader.line_num
        line_no = line_numbers[index]
        if consumed != index + 1:
            raise MeasurementFileError(path, "unterminated quote in this row", line=line_no)
        if data_lines[index].lstrip().startswith("#"):
            raise MeasurementFileError(
                path,
                "a comment line after the header",
                line=line_no,
                hint="comment lines are allowed only before the header",
            )
        if len(row) != ncol:
            _wrong_cell_count(path, row, header, line_no, data_lines[index])
        for name, k in label_cols.items():
            cell = row[k].strip()
            if not _valid_label(cell):
                what = "is empty" if not cell else f"{_escape(cell)!r} is not a valid name (no ',', quotes)"
                raise MeasurementFileError(
                    path,
                    f"the {name} {what}; every row needs its {name} (an integer or a name)",
                    line=line_no,
                    column=name,
                )
            labels[name].append(cell)
            row[k] = "0"
        for k in ignored:
            row[k] = "0"
        try:
            vals = [float(cell) for cell in row]
        except ValueError:
            vals = None
        # sum() is nan/inf when a value is; a rare overflow only costs the slow path.
        line_text = data_lines[index]
        if vals is None or "_" in line_text or not line_text.isascii() or not math.isfinite(sum(vals)):
            _check_cells(path, row, header, line_no)
            if vals is None:  # pragma: no cover - float() and _check_cells agree on what parses
                raise MeasurementFileError(path, "unreadable row", line=line_no)
        values.extend(vals)
        rows.append(line_no)
    return values, rows, labels


def _escape(text: str) -> str:
    """``text`` for a message: control characters (NUL, line breaks, escapes) written as Python escapes."""
    return "".join(c if c.isprintable() or c == " " else repr(c)[1:-1] for c in text)


def _check_cells(path: str, row: list[str], header: list[str], line: int) -> None:
    """Slow path: find the first bad cell of a row and raise (fsum overflow may bring us here)."""
    for cell, name in zip(row, header):
        text = cell.strip()
        if not text:
            raise MeasurementFileError(path, "empty cell; every column needs a value", line=line, column=name)
        try:
            value = float(text)
        except ValueError:
            value = None
        if value is None or "_" in text:
            raise MeasurementFileError(path, f"'{_escape(text)}' is not a number", line=line, column=name)
        if not text.isascii():
            # float() reads Arabic-Indic, Devanagari, full-width ... digits; a measurement file is ASCII numbers
            raise MeasurementFileError(
                path,
                f"'{_escape(text)}' is not a number: only the ASCII digits 0-9, '.', '-', '+' and 'e' make numbers "
                "in a measurement file",
                line=line,
                column=name,
            )
        if math.isnan(value):
            raise MeasurementFileError(path, f"'{_escape(text)}' is NaN; values must be finite", line=line, column=name)
        if math.isinf(value):
            raise MeasurementFileError(
                path, f"'{_escape(text)}' is infinite; values must be finite", line=line, column=name
            )


def _wrong_cell_count(
    path: str, row: list[str], header: list[str], line: int, raw: str, *, decimal_point_hint: bool = True
) -> None:
    """Raise the error for a row of ``line`` whose cell count is not the header's; ``decimal_point_hint``: suggest
    '.' as the decimal point when the raw row has digit,digit (off for formats whose decimal mark is ',')."""
    n, ncol = len(row), len(header)
    if n < ncol:
        raise MeasurementFileError(
            path,
            f"row has {n} values but the header has {ncol} columns; '{header[n]}' and after are missing",
            line=line,
            column=header[n],
        )
    hint = None
    if decimal_point_hint and re.search(r"\d,\d", raw):
        hint = "use '.' as the decimal point; ',' only separates values"
    raise MeasurementFileError(
        path,
        f"row has {n} values but the header has {ncol} columns (extra values after '{header[-1]}')",
        line=line,
        hint=hint,
    )


def _first_bad(mask: torch.Tensor, order: Sequence[int]) -> tuple[int, int]:
    """First True of an (N, k) mask in file order: by row, then by file column position."""
    row = int(mask.any(dim=1).nonzero()[0, 0])
    cols = [j for j in sorted(range(mask.shape[1]), key=lambda j: order[j]) if mask[row, j]]
    return row, cols[0]


def _check_monotonic(path: str, t: torch.Tensor, lines: list[int]) -> None:
    back = (t[1:] < t[:-1]).nonzero()
    if back.numel():
        i = int(back[0, 0]) + 1
        raise MeasurementFileError(
            path,
            f"t = {t[i].item()!r} s is earlier than {t[i - 1].item()!r} s on line {lines[i - 1]}; "
            "t must be non-decreasing within a file",
            line=lines[i],
            column="t",
        )


def _check_positive_sigma(path, sigma, lines, layout: _Layout, unit: str, names=_SIGMA) -> None:
    bad = ~(sigma > 0)
    if bad.any():
        i, j = _first_bad(bad, [layout.index[c] for c in names])
        raise MeasurementFileError(
            path,
            f"{names[j]} = {sigma[i, j].item()!r} {unit}; a standard deviation must be > 0",
            line=lines[i],
            column=names[j],
        )


def _check_rotation(path, r, lines, layout: _Layout) -> None:
    """A rotation vector longer than one turn is no orientation in radians (degrees, most likely)."""
    bad = r.norm(dim=1) > _MAX_ABS_ANGLE_RAD
    if bad.any():
        i = int(bad.nonzero()[0, 0])
        j = int(r[i].abs().argmax())
        raise MeasurementFileError(
            path,
            f"the orientation (rx, ry, rz) turns by {float(r[i].norm())!r} rad, more than one turn (2*pi); "
            "rx, ry, rz are a rotation vector in radians",
            line=lines[i],
            column=_ROTATION[j],
            hint="convert degrees to radians; rx, ry, rz are read in radians whatever --angle-unit says",
        )


def _check_length_unit(path, p, lines, layout: _Layout, unit: str) -> None:
    distance = p.norm(dim=1)
    median = distance.median().item()
    if unit == "m" and median > _MAX_MEDIAN_DISTANCE_M:
        i = int((distance > _MAX_MEDIAN_DISTANCE_M).nonzero()[0, 0])
        problem, hint = (
            f"positions look like millimetres: the median distance from the tracker origin is "
            f"{median:.6g} m, more than {_MAX_MEDIAN_DISTANCE_M:g} m",
            "if x, y, z (and sx, sy, sz) are in millimetres, pass --length-unit mm (length_unit='mm')",
        )
    elif unit == "mm" and median < _MIN_MEDIAN_DISTANCE_MM:
        i = int((distance < _MIN_MEDIAN_DISTANCE_MM).nonzero()[0, 0])
        problem, hint = (
            f"positions look like metres: the median distance from the tracker origin is {median:.6g} mm, "
            f"less than {_MIN_MEDIAN_DISTANCE_MM:g} mm, closer than a tracker measures",
            "if x, y, z (and sx, sy, sz) are in metres, pass --length-unit m (length_unit='m')",
        )
    else:
        return
    j = int(p[i].abs().argmax())
    raise MeasurementFileError(path, problem, line=lines[i], column=_POSITION[j], hint=hint)


def _check_sigma_unit(path, sigma, lines, layout: _Layout) -> None:
    median = sigma.median().item()
    if median > _MAX_MEDIAN_SIGMA_M:
        i, j = _first_bad(sigma > _MAX_MEDIAN_SIGMA_M, [layout.index[c] for c in _SIGMA])
        raise MeasurementFileError(
            path,
            f"standard deviations look like millimetres: their median is {median:.6g} m, "
            f"more than {_MAX_MEDIAN_SIGMA_M:g} m (1 cm)",
            line=lines[i],
            column=_SIGMA[j],
            hint="if x, y, z and sx, sy, sz are in millimetres, pass --length-unit mm (length_unit='mm')",
        )


def _check_angle_unit(path, q, lines, layout: _Layout, limits=None) -> None:
    bad = q.abs() > _MAX_ABS_ANGLE_RAD
    if limits is not None:
        # a joint whose limits allow more than one turn each way (a continuous joint) may read past 2 pi
        bad &= ~((limits[:, 0] < -_MAX_ABS_ANGLE_RAD) & (limits[:, 1] > _MAX_ABS_ANGLE_RAD))
    if bad.any():
        i, j = _first_bad(bad, [layout.index[c] for c in layout.joints])
        raise MeasurementFileError(
            path,
            f"{layout.joints[j]} = {q[i, j].item()!r} rad is more than one turn (2*pi); "
            "the joint readings look like degrees",
            line=lines[i],
            column=layout.joints[j],
            hint="if q1..qN are in degrees, pass --angle-unit deg (angle_unit='deg')",
        )


def _check_ranges(path, p, sigma, temperature, lines, layout: _Layout, unit: str) -> None:
    """Refuse values no measurement has (in SI units, after conversion): a position or standard deviation beyond
    :data:`MAX_POSITION_M` (1000 km), a temperature outside :data:`TEMPERATURE_RANGE_C` (-100 .. 200 degC).

    Such a value is a typo or a broken export; fitted, it would swamp every other row (or overflow the squares).
    """
    shown = LENGTH_UNITS[unit]
    for names, values, what in ((_POSITION, p, "a position"), (_SIGMA, sigma, "a standard deviation")):
        if values is None:
            continue
        bad = values.abs() > MAX_POSITION_M
        if bad.any():
            i, j = _first_bad(bad, [layout.index[c] for c in names])
            raise MeasurementFileError(
                path,
                f"{names[j]} = {values[i, j].item() * shown!r} {unit} is beyond {MAX_POSITION_M * shown:g} {unit} "
                f"(1000 km), not {what} a laser tracker measures",
                line=lines[i],
                column=names[j],
            )
    if temperature is not None:
        lo, hi = TEMPERATURE_RANGE_C
        bad = (temperature < lo) | (temperature > hi)
        if bad.any():
            i = int(bad.nonzero()[0, 0])
            raise MeasurementFileError(
                path,
                f"temperature = {temperature[i].item()!r} degC is outside {lo:g} .. {hi:g} degC",
                line=lines[i],
                column="temperature",
                hint="the temperature column is in degrees Celsius",
            )


def _check_degrees_are_not_radians(path, q, lines, layout: _Layout, limits=None) -> None:
    """Refuse radians declared as degrees: every reading within one turn *as a number of degrees* (|q| <= 2 pi)
    while the readings do move (the largest is beyond :data:`_MIN_DEGREES_MOVED`) and the robot's limits span
    more than a few degrees.

    Read as degrees such a file keeps every joint within +-6.3 deg of zero, which no calibration campaign or robot
    program does; read as radians it is an ordinary campaign. A file of (near) zeros, such as the home pose alone,
    says nothing either way and passes.
    """
    largest = float(q.abs().max())
    if not _MIN_DEGREES_MOVED < largest <= _MAX_ABS_ANGLE_RAD:
        return
    if limits is not None:
        span = (limits[:, 1] - limits[:, 0]).clamp(max=4 * math.pi)
        if not bool((span > 2 * math.radians(_MAX_ABS_ANGLE_RAD)).any()):
            return  # a robot whose joints only move a few degrees: small degree values are all it has
    i, j = _first_bad(q.abs() == largest, [layout.index[c] for c in layout.joints])
    raise MeasurementFileError(
        path,
        f"the joint readings look like radians although degrees were declared: every |q| is at most 2*pi "
        f"(the largest, {layout.joints[j]} = {q[i, j].item()!r}), so as degrees the robot would never move more "
        f"than {_MAX_ABS_ANGLE_RAD:.3g} deg from zero on any joint",
        line=lines[i],
        column=layout.joints[j],
        hint="if q1..qN are in radians, leave out --angle-unit deg (angle_unit='rad' is the default)",
    )


def _check_joint_limits(path, q, lines, layout: _Layout, limits, angle_unit, robot_name, linear, length_unit) -> None:
    lower, upper = limits[:, 0], limits[:, 1]
    bad = (q < lower - _JOINT_LIMIT_TOL) | (q > upper + _JOINT_LIMIT_TOL)
    if not bad.any():
        return
    i, j = _first_bad(bad, [layout.index[c] for c in layout.joints])
    name = layout.joints[j]
    value, lo, hi = q[i, j].item(), lower[j].item(), upper[j].item()
    # twelve digits and the excess: a reading a few micro-radians past a limit printed to six digits looked
    # equal to the limit it was refused for
    excess, side = (lo - value, "below") if value < lo else (value - hi, "above")
    if bool(linear[j]):  # a prismatic joint: metres, and the file's unit where it is another
        factor = LENGTH_UNITS[length_unit]
        shown = f"{value:.12g} m" if factor == 1.0 else f"{value * factor:.12g} {length_unit} ({value:.12g} m)"
        bounds, unit = f"[{lo:.12g}, {hi:.12g}] m", "m"
    elif angle_unit == "deg":
        shown = f"{math.degrees(value):.12g} deg ({value:.12g} rad)"
        bounds = f"[{math.degrees(lo):.12g}, {math.degrees(hi):.12g}] deg"
        unit = f"deg ({excess:.3g} rad)"
        excess = math.degrees(excess)
    else:
        shown = f"{value:.12g} rad"
        bounds, unit = f"[{lo:.12g}, {hi:.12g}] rad", "rad"
    whose = f"robot '{robot_name}'" if robot_name else "the robot"
    raise MeasurementFileError(
        path,
        f"{name} = {shown} is outside the limits of {whose}, {bounds}: {excess:.3g} {unit} {side} it",
        line=lines[i],
        column=name,
    )


# --------------------------------------------------------------------------- writing


def _format_row(values: Sequence[float | str]) -> str:
    # repr(float) is the shortest text that reads back to the same double: round trips are exact.
    return ",".join([v if isinstance(v, str) else repr(v) for v in values]) + "\n"


def write_measurements(
    path: str | os.PathLike,
    m: Measurements,
    *,
    meta: Mapping[str, str] | None = None,
    columns: Sequence[str] | None = None,
    written_by: str | None = None,
    labels: Mapping[str, tuple[str, ...]] | None = None,
) -> None:
    """Write ``m`` in the contract format, SI units, atomically.

    The header is ``q1..qN,x,y,z[,t][,temperature][,sx,sy,sz][,rx,ry,rz][,srx,sry,srz][,extra...]`` (x, y, z left
    out when ``m.p`` is None). Values are written with ``repr(float)``, so reading the file
    back gives bit-identical tensors. The file is written to a temporary file in the same
    directory and moved into place with ``os.replace``: a failure never leaves partial output.

    Args:
        path: the file to write (replaced if it exists).
        m: the measurements.
        meta: ``# key: value`` lines; merged over ``m.meta`` (its keys win).
        columns: the columns to write and their order (default: all, in the order above).
        written_by: the command writing the file (``torchcal predict``): written as the first line,
            ``# written_by: ...``, the mark by which ``--out`` knows a file torchcal may replace.
        labels: extra columns written as names: ``m.extra[key]`` holds each row's index into ``labels[key]``
            (predict's ``model`` column).

    Raises:
        OptionError: a name in ``columns`` that ``m`` does not have.
        MeasurementFileError: a non-finite value, a meta entry that cannot be written, or the
            file cannot be written.
    """
    path_str = str(path)
    available, names = _writable_columns(m, labels)
    columns = _chosen_columns(columns, available)
    head = _meta_lines(path_str, {**m.meta, **(meta or {})}, written_by)
    head.append(",".join(columns) + "\n")

    table = torch.stack([available[c] for c in columns], dim=1) if columns else torch.empty(m.n, 0)
    finite = torch.isfinite(table)
    if not finite.all():
        i, j = _first_bad(~finite, list(range(len(columns))))
        raise MeasurementFileError(
            path_str,
            f"cannot write {table[i, j].item()!r}: values must be finite",
            line=len(head) + i + 1,
            column=columns[j],
        )

    rows = table.tolist()
    for j, c in enumerate(columns):  # a label column's cells are its names
        if c in names:
            for row in rows:
                row[j] = names[c][int(row[j])]
    _atomic_write(path_str, head, rows)


def _writable_columns(m: Measurements, labels) -> tuple[dict[str, torch.Tensor], dict[str, tuple[str, ...]]]:
    """Every column ``m`` can be written with, in the contract's order, and the names of its label columns (a
    label column holds each row's index into them)."""
    available: dict[str, torch.Tensor] = {f"q{k + 1}": m.q[:, k] for k in range(m.dof)}
    if m.p is not None:
        available.update({c: m.p[:, k] for k, c in enumerate(_POSITION)})
    if m.t is not None:
        available["t"] = m.t
    if m.temperature is not None:
        available["temperature"] = m.temperature
    if m.sigma is not None:
        available.update({c: m.sigma[:, k] for k, c in enumerate(_SIGMA)})
    if m.r is not None:
        available.update({c: m.r[:, k] for k, c in enumerate(_ROTATION)})
    if m.sigma_r is not None:
        available.update({c: m.sigma_r[:, k] for k, c in enumerate(_ROTATION_SIGMA)})
    available.update(m.extra)
    names: dict[str, tuple[str, ...]] = {}
    for label in _LABELS:
        index = getattr(m, label)
        if index is not None:
            available[label] = index.to(torch.float64)
            names[label] = getattr(m, f"{label}_names")
    for key, label_names in (labels or {}).items():
        names[key] = tuple(label_names)
    return available, names


def _chosen_columns(columns: Sequence[str] | None, available: dict) -> list[str]:
    """The columns asked for (default: all available), each available and named once."""
    if columns is None:
        return list(available)
    columns = list(columns)
    unknown = [c for c in columns if c not in available]
    if unknown:
        raise OptionError(f"cannot write column(s) {', '.join(map(repr, unknown))}; valid: {', '.join(available)}")
    if len(set(columns)) != len(columns):
        raise OptionError(f"columns lists a name twice: {columns}")
    return columns


def _meta_lines(path_str: str, merged: dict, written_by: str | None) -> list[str]:
    """The ``# key: value`` lines, ``written_by`` first; refused where a key or value cannot be read back."""
    if written_by is not None:  # first, whatever the metadata read from an earlier file held
        merged = {"written_by": written_by, **{k: v for k, v in merged.items() if k != "written_by"}}
    head = []
    for key, value in merged.items():
        key, value = str(key), str(value)
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.\-]*", key) or "\n" in value or "\r" in value:
            raise MeasurementFileError(
                path_str,
                f"meta entry {key!r}: {value!r} cannot be written as a '# key: value' line "
                "(keys are letters, digits, '_', '.', '-'; values are one line)",
            )
        head.append(f"# {key}: {value}\n")
    return head


def _atomic_write(path: str, head: list[str], rows: list[list[float]]) -> None:
    target = Path(path)
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)  # a new folder, as every command's --out makes it
        # os.open with 0o666 lets the umask decide the permissions, as for a plain open().
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except OSError as err:
        raise MeasurementFileError(path, f"cannot write the file: {err.strerror or err}") from err
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            f.writelines(head)
            for row in rows:
                f.write(_format_row(row))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException as err:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(err, OSError):
            raise MeasurementFileError(path, f"cannot write the file: {err.strerror or err}") from err
        raise
