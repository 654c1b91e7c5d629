"""The load columns of a measurement file: the payload a row was measured with and the joint torques it read.

Contract section 1: ``payload`` [kg] is the mass carried at the flange (0 where the column is absent),
``payload_x, payload_y, payload_z`` [m] its centre of mass in the flange frame (absent: at the probe), and
``tau1..tauN`` [N m, N for a prismatic joint] the torque (force) each joint's drive applies to hold the arm, as
the controller measured it. They travel in :attr:`Measurements.extra <torchcal.data.Measurements.extra>` under these
names, so that every command that copies rows keeps them; the readers validate them here.

Sign convention of the torques: ``tau_j`` is the torque the drive applies about joint j's axis (right hand, the
axis of the robot description) to hold the arm against gravity; a static arm's ``tau`` is then
:meth:`~torchcal.robot.RobotModel.gravity_torques` with the opposite sign of the weight's moment, and the
compliance read from it (``dq_j = k_j tau_j``) takes its sign from the data (one fitted ``k_j`` per joint).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import torch

from torchcal._bounds import MAX_PAYLOAD_KG
from torchcal.errors import MeasurementFileError

Tensor = torch.Tensor

PAYLOAD = "payload"
PAYLOAD_COM = ("payload_x", "payload_y", "payload_z")
TAU_RE = re.compile(r"tau([0-9]+)")
#: the farthest a payload's centre of mass may lie from the flange [m]: beyond it the unit is millimetres
MAX_PAYLOAD_OFFSET_M = 5.0
#: the largest joint torque a row may hold [N m]: beyond it the unit is N mm (or a typo); the largest arms' base
#: joints hold about 5e4 N m
MAX_TORQUE_NM = 1e6
#: the divisor that turns a payload offset in the file's length unit into metres (the reader's ``LENGTH_UNITS``)
_LENGTH_DIVISOR = {"m": 1.0, "mm": 1000.0}


def is_load_column(name: str) -> bool:
    """Whether ``name`` is one of the contract's load columns."""
    return name == PAYLOAD or name in PAYLOAD_COM or TAU_RE.fullmatch(name) is not None


def torque_columns(names: Sequence[str]) -> list[str]:
    """The ``tau<k>`` names among ``names``, ordered by k."""
    found = [(int(mt.group(1)), n) for n in names if (mt := TAU_RE.fullmatch(n))]
    return [n for _, n in sorted(found)]


def payload_of(extra: Mapping[str, Tensor]) -> Tensor | None:
    """Each row's payload ``(N,)`` [kg], or None without a ``payload`` column."""
    return extra.get(PAYLOAD)


def payload_com_of(extra: Mapping[str, Tensor]) -> Tensor | None:
    """Each row's payload centre of mass in the flange frame ``(N, 3)`` [m], or None (at the probe)."""
    if not all(c in extra for c in PAYLOAD_COM):
        return None
    return torch.stack([extra[c] for c in PAYLOAD_COM], dim=1)


def torques_of(extra: Mapping[str, Tensor]) -> Tensor | None:
    """Each row's measured joint torques ``(N, dof)`` [N m or N], or None without ``tau`` columns."""
    names = torque_columns(list(extra))
    if not names:
        return None
    return torch.stack([extra[n] for n in names], dim=1)


def check_load(
    path: str, extra: dict[str, Tensor], lines: Sequence[int], header_line: int, dof: int, length_unit: str
) -> dict[str, Tensor]:
    """Validate the load columns of a file read into ``extra`` (in the file's units) and return ``extra`` with the
    payload's centre of mass in metres.

    Raises:
        MeasurementFileError: a negative or absurd payload, a centre of mass given in part, without a payload or
            beyond :data:`MAX_PAYLOAD_OFFSET_M`, torque columns with gaps or another count than the joints, a torque
            beyond :data:`MAX_TORQUE_NM` (each names the file, line and column).
    """
    extra = dict(extra)
    present = [c for c in PAYLOAD_COM if c in extra]
    if present and len(present) != 3:
        missing = next(c for c in PAYLOAD_COM if c not in extra)
        raise MeasurementFileError(
            path,
            f"the payload's centre of mass needs all of {', '.join(PAYLOAD_COM)}",
            line=header_line,
            column=missing,
        )
    if present and PAYLOAD not in extra:
        raise MeasurementFileError(
            path, "payload_x, payload_y, payload_z need the payload column (kg)", line=header_line, column=PAYLOAD
        )
    if PAYLOAD in extra:
        _check_payload(path, extra[PAYLOAD], lines)
    if present:
        for c in PAYLOAD_COM:
            extra[c] = extra[c] / _LENGTH_DIVISOR[length_unit]
        _check_bound(path, extra, PAYLOAD_COM, lines, MAX_PAYLOAD_OFFSET_M, "m", "a payload's offset from the flange")
    names = torque_columns(list(extra))
    if names:
        _check_torque_names(path, names, header_line, dof)
        _check_bound(path, extra, names, lines, MAX_TORQUE_NM, "N m", "a joint torque")
    return extra


def _check_payload(path: str, payload: Tensor, lines: Sequence[int]) -> None:
    bad = (payload < 0) | (payload > MAX_PAYLOAD_KG)
    if not bool(bad.any()):
        return
    i = int(bad.nonzero()[0, 0])
    value = float(payload[i])
    why, hint = (
        ("a payload is a mass, >= 0", "write 0 for a row measured without load")
        if value < 0
        else (f"more than {MAX_PAYLOAD_KG:g} kg", "the payload column is in kilograms, not grams")
    )
    raise MeasurementFileError(path, f"payload = {value!r} kg: {why}", line=lines[i], column=PAYLOAD, hint=hint)


def _check_bound(path, extra, names, lines, bound: float, unit: str, what: str) -> None:
    values = torch.stack([extra[n] for n in names], dim=1)
    bad = values.abs() > bound
    if not bool(bad.any()):
        return
    i, j = (int(v) for v in bad.nonzero()[0])
    raise MeasurementFileError(
        path,
        f"{names[j]} = {float(values[i, j])!r} {unit} is beyond {bound:g} {unit}, not {what}",
        line=lines[i],
        column=names[j],
        hint="payload_x, payload_y, payload_z follow the length unit (--length-unit, length_unit=); tau1..tauN are in "
        "N m (N for a prismatic joint)",
    )


def _check_torque_names(path: str, names: list[str], header_line: int, dof: int) -> None:
    numbers = [int(TAU_RE.fullmatch(n).group(1)) for n in names]
    for k, (number, name) in enumerate(zip(numbers, names), start=1):
        if name != f"tau{number}" or number != k:
            raise MeasurementFileError(
                path,
                f"torque columns are tau1..tauN without gaps or leading zeros (found {', '.join(names)})",
                line=header_line,
                column=name,
            )
    if dof and len(names) != dof:
        raise MeasurementFileError(
            path,
            f"file has {len(names)} torque columns (tau1..tau{len(names)}) but {dof} joint columns: "
            "one torque per joint",
            line=header_line,
            column=f"tau{min(len(names), dof) + 1}",
        )
