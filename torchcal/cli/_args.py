"""The argument types and the options several commands share: one place for each flag's words and bounds."""

from __future__ import annotations

import argparse
import math

from torchcal._bounds import (
    MAX_PAYLOAD_KG,
    MAX_RANK_TOL,
    MAX_SIGMA_ANGLE,
    MAX_SIGMA_JOINT,
    MAX_SIGMA_LENGTH,
    MAX_SIGMA_TORQUE,
    MAX_SIGMA_TRACKER,
)
from torchcal._method import METHODS


def _number(kind: str, high: float | None = None):
    """An argparse type: a finite float that is positive (``kind='positive'``), >= 0 or in (0, 1), and at most
    ``high`` where given."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if kind == "positive" and v <= 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        if kind == "nonnegative" and v < 0:
            raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
        if kind == "fraction" and not 0 < v < 1:
            raise argparse.ArgumentTypeError(f"must be between 0 and 1 (exclusive), got {text}")
        if high is not None and v > high:
            raise argparse.ArgumentTypeError(f"must be <= {high:g}, got {text}")
        return v

    parse.__name__ = f"{kind} number"
    return parse


def _tool(text: str) -> tuple[float, float, float]:
    """``X,Y,Z`` in mm -> metres."""
    parts = text.split(",")
    try:
        xyz = tuple(float(v) * 1e-3 for v in parts)
    except ValueError:
        xyz = ()
    if len(xyz) != 3 or not all(math.isfinite(v) for v in xyz):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in mm (three numbers), got '{text}'")
    return xyz


#: Most poses or trajectory samples ``simulate`` makes: a campaign of that size takes minutes; a larger one
#: would run for hours or exhaust memory before it could be written.
MAX_SAMPLES = 100_000
#: Seeds are in 0..2**63 - 1: each use adds a small stream number (:class:`torchcal.stats.Stream`) and a torch
#: generator takes at most 2**64 - 1.
MAX_SEED = 2**63 - 1


def _whole(text: str) -> int:
    """``text`` as a whole number; ``1e6`` is accepted when it is one (so ``1e12`` is told it is too large)."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not math.isfinite(v) or v != int(v):
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}")
    return int(v)


def _count(text: str) -> int:
    v = _whole(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    if v > MAX_SAMPLES:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_SAMPLES:,}, got {text}")
    return v


def _seed(text: str) -> int:
    v = _whole(text)
    if not 0 <= v <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be a whole number from 0 to 2**63 - 1 ({MAX_SEED}), got {text}")
    return v


def _joint_numbers(text: str) -> tuple[int, ...]:
    """A comma-separated list of 1-based joint numbers, e.g. ``1,4,5,6``."""
    try:
        joints = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected joint numbers with commas, e.g. 1,4,5,6, got {text!r}") from None
    if min(joints) < 1 or len(set(joints)) != len(joints):
        raise argparse.ArgumentTypeError(f"expected distinct joint numbers from 1, got {text!r}")
    return joints


_count.__name__ = "count"
_seed.__name__ = "seed"
_joint_numbers.__name__ = "joints"
POSITIVE, NONNEG, FRACTION = _number("positive"), _number("nonnegative"), _number("fraction")
# the library's bounds (torchcal._bounds) in the command's units: um, deg, mm
TRACKER_UM = _number("positive", MAX_SIGMA_TRACKER * 1e6)
TRACKER_UM_SIM = _number("nonnegative", MAX_SIGMA_TRACKER * 1e6)
JOINT_DEG = _number("nonnegative", math.degrees(MAX_SIGMA_JOINT))
ORIENTATION_DEG = _number("positive", 5.0)
RANK_TOL = _number("positive", MAX_RANK_TOL)
LENGTH_BIAS_MM = _number("nonnegative", MAX_SIGMA_LENGTH * 1e3)
ANGLE_BIAS_DEG = _number("nonnegative", math.degrees(MAX_SIGMA_ANGLE))
PAYLOAD_KG = _number("nonnegative", MAX_PAYLOAD_KG)  # 5000 is grams: the payload column refuses it too
TORQUE_NOISE_NM = _number("nonnegative", MAX_SIGMA_TORQUE)
#: what happens to an existing --out directory, said once for every command that writes one
REPLACED_HELP = (
    "an existing one is replaced only when it is an earlier torchcal output (marked by .torchcal-run), anything "
    "else is refused"
)
OUT_HELP = "output directory; " + REPLACED_HELP
#: the same, after a help text that already says what the directory is
OUT_REPLACED = REPLACED_HELP[:1].upper() + REPLACED_HELP[1:]


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no messages on stderr")
    p.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="print the full traceback of an unexpected error",
    )


def _add_robot(p: argparse.ArgumentParser, required: bool = True) -> None:
    p.add_argument(
        "--robot",
        required=required,
        default=None if required else "ur5",
        help="built-in name (ur5, ur10, panda, ...), a URDF file or a DH YAML file",
    )
    p.add_argument("--base-link", default=None, help="URDF: first link of the chain (default: the root)")
    p.add_argument("--tip-link", default=None, help="URDF: last link of the chain (default: the only deepest leaf)")


def _add_force(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out file that torchcal did not write (files torchcal wrote start with "
        "'# written_by: torchcal'; they are replaced without it)",
    )


def _add_device(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device",
        default="cpu",
        help="where to compute: cpu (default), cuda or cuda:N (float64 throughout; results are written from CPU "
        "copies)",
    )


def _add_computing(p: argparse.ArgumentParser) -> None:
    """``--device``, the unit options and the common ones: what every command that computes with a model takes."""
    _add_device(p)
    _add_units(p)
    _add_common(p)


def _add_units(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--length-unit",
        choices=["m", "mm"],
        default="m",
        help="unit of x,y,z,sx,sy,sz and of prismatic joints' columns (default m)",
    )
    p.add_argument(
        "--angle-unit", choices=["rad", "deg"], default="rad", help="unit of the revolute joints' columns (default rad)"
    )


#: calibrate's methods and the integrated method's engines (declared once, in a module without torch)
METHOD_CHOICES = METHODS
