"""The ``torchcal`` command. Messages go to stderr, results to files under ``--out``.

Exit codes: 0 success; 2 a usage error or a :class:`~torchcal.errors.TorchcalError` (bad input, option or
file, with a message saying what was expected and what came); 1 an unexpected internal error (a one-line
summary and where to report it; the traceback with ``--debug``); 130 interrupted.
"""

from __future__ import annotations

import argparse
import errno
import functools
import json
import math
import sys
import traceback
import warnings
from pathlib import Path

import torch

from torchcal import _console
from torchcal._bounds import (
    MAX_RANK_TOL,
    MAX_SIGMA_ANGLE,
    MAX_SIGMA_JOINT,
    MAX_SIGMA_LENGTH,
    MAX_SIGMA_TRACKER,
    SIGMA_JOINT,
)
from torchcal._device import resolve_device
from torchcal._method import DEFAULT_METHOD, ENGINES, METHODS, Engine
from torchcal._outdir import check_out_dir, check_out_file
from torchcal._threads import torch_threads
from torchcal._version import __version__
from torchcal.errors import OptionError, TorchcalError

F64 = torch.float64

#: Where unexpected errors should be reported (printed with the one-line summary).
REPORT_TO = "the torchcal issue tracker (see README.md, 'Reporting problems')"


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


def _add_import_export(sub) -> None:
    """``convert`` (other layouts in) and ``export`` (the calibration out to other software)."""
    cv = sub.add_parser(
        "convert",
        help="import measurements in another layout (--map) or a third-party data set (--from)",
        description="Write a torchcal measurement file (CSV) from measurements in other layouts. --map MAP.yaml: "
        "joints and points in one file or several (text with any delimiter, header or not; YAML; MATLAB .mat), "
        "their units, joint order, signs and offsets, 4x4 or quaternion poses, several reflectors (probe) or "
        "placements (station), extra columns kept, as the MAP describes (docs/reference.md, 'Importing "
        "measurements'). --from ipa-robot-accuracy: the public UR10 data set.",
    )
    cv.add_argument("inputs", nargs="+", metavar="INPUT", help="the file(s) to convert; the MAP numbers them from 1")
    cv.add_argument("--map", default=None, metavar="MAP.yaml", help="the YAML file that describes the inputs' layout")
    cv.add_argument(
        "--from",
        dest="fmt",
        default=None,
        choices=["ipa-robot-accuracy"],
        help="ipa-robot-accuracy: Series_*/measurements_*.csv of the UR10 + Leica data set "
        "(Landgraf et al., IEEE CASE 2021, MIT licence)",
    )
    cv.add_argument("--out", required=True, help="measurement file to write")
    _add_force(cv)
    _add_common(cv)

    ex = sub.add_parser(
        "export",
        help="write a calibrated run's geometry for other software (UR ROS 2 driver, DH table, URDF)",
        description="Write the calibrated chain of a run directory in another software's format. ur-ros2: the UR "
        "ROS 2 driver's kinematics parameter file (as ur_calibration writes it: per joint x, y, z, roll, pitch, yaw "
        "under 'kinematics'; base_link_inertia is the run's base frame, tool0 its flange); a robot that is not six "
        "revolute joints, or whose flange is off the last axis, is refused. dh: a DH / MDH robot file that --robot "
        "loads back with the same forward kinematics (DH robots). urdf: the calibrated URDF with the probe and "
        "tracker frames. The instrument pose, lever arm and non-geometric effects stay in the run (report.json).",
    )
    ex.add_argument("run", help="run directory written by calibrate (or station)")
    ex.add_argument("--format", required=True, choices=("ur-ros2", "dh", "urdf"), help="the file to write")
    ex.add_argument("--out", required=True, help="file to write")
    ex.add_argument(
        "--geometry",
        choices=("standalone", "cofitted"),
        default="standalone",
        help="for a run with effects, which no file can carry: standalone (default) writes the chain that predicts "
        "best without them (the run's kinematic calibration or a refit to the full model, whichever is better on the "
        "held-out rows); cofitted writes the geometry fitted together with the effects, for software that applies "
        "them itself. The header and stderr give the held-out error of the file alone and of the full run",
    )
    _add_force(ex)
    _add_common(ex)

    ce = sub.add_parser(
        "check-export",
        help="load an exported DH or URDF file back and compare it with its run",
        description="Load FILE (a DH YAML or URDF file written by torchcal export) as --robot loads it and print the "
        "largest difference of its chain to the run's exported chain (flange and probe, at the run's held-out joints) "
        "and the held-out RMSE of the file's chain with the run's instrument pose and lever arm.",
    )
    ce.add_argument("run", help="run directory written by calibrate (or station)")
    ce.add_argument("file", help="the exported file (.yaml, .yml or .urdf)")
    ce.add_argument(
        "--geometry",
        choices=("standalone", "cofitted"),
        default=None,
        help="compare with this chain of the run (default: whichever is closer to the file)",
    )
    _add_common(ce)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchcal", description="Robot arm calibration from laser-tracker data.")
    parser.add_argument("--debug", action="store_true", help="print the full traceback of an unexpected error")
    parser.add_argument("--version", action="version", version=f"torchcal {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser(
        "simulate",
        help="simulate a laser-tracker campaign (train.csv, test.csv, truth.json)",
        description="Simulate a laser-tracker campaign: biased geometry, unknown tracker pose and lever "
        "arm, tracker and joint noise, and the non-geometric effects asked for.",
    )
    _add_robot(s)
    s.add_argument("--out", required=True, help=OUT_HELP)
    s.add_argument("--poses", type=_count, default=800, help="static poses in train.csv (default 800)")
    s.add_argument("--test-poses", type=_count, default=200, help="static poses in test.csv (default 200)")
    s.add_argument(
        "--trajectory",
        action="store_true",
        help="a continuous trajectory instead of static poses (train = first --train-samples)",
    )
    s.add_argument(
        "--path",
        default="p2p",
        choices=("p2p", "multisine", "randomwalk", "sweeps"),
        help="trajectory family: p2p (point-to-point program, default), multisine (smooth, never "
        "repeating, most of the joint range), randomwalk (slow), sweeps (one cycle repeated)",
    )
    s.add_argument("--samples", type=_count, default=7342, help="trajectory samples (default 7342, as the paper)")
    s.add_argument("--train-samples", type=_count, default=5874, help="trajectory samples for training (default 5874)")
    s.add_argument(
        "--seed", type=_seed, default=0, help="random seed, 0 to 2**63 - 1; the campaign is reproducible from it"
    )
    s.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="KIND[:JOINT][=SIZE]",
        help="inject an effect; repeatable. KIND: compliance, backlash, cyclic (need :JOINT), "
        "coupling (:J<-K, joint J's reading picks up a share of joint K's), "
        "drift (:t or :temperature), field (smooth 6-29-3 network field). SIZE is the RMS probe "
        "displacement with a unit, e.g. compliance:2=50um, coupling:3<-2=50um, field=0.6mm",
    )
    s.add_argument(
        "--tracker-noise", type=TRACKER_UM_SIM, default=15.0, help="tracker noise per axis [um], <= 10000 (default 15)"
    )
    s.add_argument(
        "--joint-noise", type=JOINT_DEG, default=0.0005, help="joint reading noise [deg], <= 1 (default 0.0005)"
    )
    s.add_argument("--length-bias", type=LENGTH_BIAS_MM, default=0.1, help="sigma of the geometric length biases [mm]")
    s.add_argument("--angle-bias", type=ANGLE_BIAS_DEG, default=0.01, help="sigma of the geometric angle biases [deg]")
    s.add_argument(
        "--orientation",
        type=ORIENTATION_DEG,
        default=None,
        metavar="DEG",
        help="a 6-D probe (a T-Mac): write its orientation rx,ry,rz [rad] (and srx,sry,srz) with this noise per "
        "axis [deg], e.g. 0.01",
    )
    s.add_argument("--no-sigma", action="store_true", help="leave out the sx,sy,sz columns")
    s.add_argument(
        "--length-unit",
        choices=["m", "mm"],
        default="m",
        help="unit of x,y,z,sx,sy,sz and prismatic joints in the files (default m)",
    )
    s.add_argument(
        "--fixed-tool-axis",
        type=POSITIVE,
        default=None,
        metavar="DEG",
        help="static poses whose tool axis turns by at most DEG degrees (e.g. 0.03: a lifting-column robot "
        "measured by a total station; with --stations, each placement's axis faces its own instrument), plus "
        "turned.csv: poses with the tool turned at least 30 deg away",
    )
    s.add_argument(
        "--stations",
        type=int,
        default=1,
        metavar="K",
        help="K instrument placements, each measuring an equal share of the poses (a station column S1..SK)",
    )
    s.add_argument(
        "--probes",
        type=int,
        default=1,
        metavar="P",
        help="P reflectors on a nest at the flange, every pose measured by each (a probe column P1..PP)",
    )
    _add_load_options(s)
    s.add_argument(
        "--narrow",
        type=_joint_numbers,
        default=(),
        metavar="JOINTS",
        help="a narrow campaign: these joints (e.g. 1,4,5,6) of the training poses stay within --width-deg of one "
        "pose's while the others range; the test poses range over the whole workspace",
    )
    s.add_argument(
        "--width-deg",
        type=POSITIVE,
        default=1.0,
        metavar="W",
        help="with --narrow: the width of each held joint's band [deg] (default 1)",
    )
    _add_common(s)

    c = sub.add_parser(
        "calibrate",
        help="fit the robot to measurements and write a run directory",
        description="Fit the robot to laser-tracker measurements (a CSV file: q1..qN, x, y, z, "
        "optional t, temperature, sx, sy, sz, rx, ry, rz, station, probe) and write the run "
        "directory: report.json, report.md with plots, robot_calibrated.urdf, model for predict.",
    )
    c.add_argument(
        "data",
        help="measurement file (CSV with a header row q1..qN,x,y,z[,t][,temperature][,sx,sy,sz]"
        "[,rx,ry,rz[,srx,sry,srz]][,station][,probe]; '# key: value' comment lines before it; "
        "torchcal convert imports other layouts)",
    )
    _add_robot(c)
    c.add_argument("--out", required=True, help="run directory to write; " + REPLACED_HELP)
    c.add_argument(
        "--method",
        default=None,
        choices=METHOD_CHOICES,
        help="auto (default: geometry, then the named effects (joint compliance, backlash, cyclic joint errors, "
        "transmission, drift) that the residuals demand and validation poses confirm, then a learned residual model "
        "where validation data demand it), "
        "kinematic, pcm (paper Eq. 10 + network), kinematic+ann (kinCalib+), "
        "integrated (the paper's ANN-EKF; needs a continuous trajectory with a monotonic t column)",
    )
    c.add_argument(
        "--engine",
        choices=ENGINES,
        default=Engine.AUTO.value,
        help="integrated method: auto (default: the engines and their settings, and geometry alone, "
        "judged on the last 20 %% of the training samples; the best is kept only if it beats geometry), "
        "adaptive (geometry and network in one filter state) or ekf (the paper's filter on the kinematic "
        "calibration's geometry)",
    )
    c.add_argument("--seed", type=_seed, default=0, help="seed of the held-out split and the network (0 to 2**63 - 1)")
    c.add_argument("--holdout", type=FRACTION, default=0.2, help="held-out fraction (default 0.2)")
    c.add_argument(
        "--prior",
        metavar="RUN",
        default=None,
        help="start from a calibrated run directory and update it from these rows (kinematic, MAP about its values "
        "with its covariance; as few as 5 rows; report.json 'prior' names the parameters that moved; the rows' "
        "stations and probes are matched to the run's by label, new ones fitted from scratch). With few rows "
        "the held-out error is of one or two rows: judge the update on a separate check file (torchcal predict)",
    )
    c.add_argument(
        "--refit",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="write the model fitted again on all samples, training and held-out, once chosen (the held-out errors "
        "reported stay those of the fit on the training samples; on a trajectory the held-out last samples are the "
        "nearest to its continuation). Default: on for --method integrated with --engine auto, off otherwise; "
        "--refit is allowed for kinematic too",
    )
    c.add_argument(
        "--tracker-noise",
        type=TRACKER_UM,
        default=15.0,
        help="tracker noise per axis [um] when the file has no sx,sy,sz, <= 10000 (default 15)",
    )
    c.add_argument(
        "--orientation-noise",
        type=ORIENTATION_DEG,
        default=None,
        help="a 6-D probe's orientation noise per axis [deg] when the file has rx,ry,rz but no srx,sry,srz, "
        "in (0, 5] (default 0.01)",
    )
    c.add_argument(
        "--joint-noise", type=JOINT_DEG, default=0.0005, help="joint reading noise [deg], <= 1 (default 0.0005)"
    )
    c.add_argument(
        "--rank-tol", type=RANK_TOL, default=None, help="identifiability tolerance, in (0, 0.01] (default 1e-6)"
    )
    c.add_argument(
        "--max-joint-error",
        type=POSITIVE,
        default=5.0,
        help="the largest size [mrad; mm on a prismatic joint] a named joint-angle effect (cyclic, transmission, "
        "compliance, backlash) may have anywhere on its joint's range; larger ones are rejected (default 5)",
    )
    c.add_argument(
        "--tool",
        type=_tool,
        default=None,
        metavar="X,Y,Z",
        help="the known lever arm [mm] (probe in the flange frame): the prior's centre; an element the data do "
        "not determine better than --tool-sigma is held at it (default: unknown, 500 mm prior about the flange)",
    )
    c.add_argument("--tool-sigma", type=POSITIVE, default=1.0, help="sigma of --tool [mm] (default 1)")
    _add_computing(c)

    pr = sub.add_parser(
        "predict",
        help="predict probe positions with a calibrated run",
        description="Predict the probe position in the tracker frame for every row of DATA with "
        "everything the run learned (geometry, effects, network); each row's station and probe columns are honoured "
        "(by name; absent: the run's first) and kept in the output, and a name the run lacks is refused.",
    )
    pr.add_argument("run", help="run directory written by calibrate")
    pr.add_argument("data", help="file with q1..qN (and t, temperature when the run uses them)")
    pr.add_argument(
        "--out",
        required=True,
        help="CSV to write: x,y,z [m], the trust columns sx,sy,sz [m] and extrapolation (sx,sy,sz: the standard "
        "deviation of a new measurement minus the prediction) and model (full, or geometric: the run's kinematic "
        "calibration beyond the region where it is far surer), plus the q*, t, station and probe columns (never one "
        "of the input files)",
    )
    _add_force(pr)
    _add_computing(pr)

    cp = sub.add_parser(
        "compensate",
        help="joint commands that reach targets by the calibrated model",
        description="For every row of TARGETS (x,y,z in the instrument frame, and/or nominal joints "
        "q1..qN of a robot program), write the joint commands that the calibrated model (geometry, "
        "effects, learned correction) says put the probe there, with the remaining miss and a "
        "status (converged, limit, unreachable). x,y,z with q1..qN: reach x,y,z starting from q. "
        "q1..qN alone: reach the point (and the tool orientation) the nominal model gives q. x,y,z alone: start "
        "from --start or from the nominal inverse kinematics. With orientation targets (rx,ry,rz, or program "
        "joints alone) and a run that fitted the probe's orientation, the full pose is solved and the orientation "
        "miss written beside the position miss (--position-only: positions only). t and temperature columns feed "
        "effects that read them; station and probe columns place each row (a run of several). The output keeps "
        "the file's joints as q1_program..qN_program, and is in the file's units (--length-unit, --angle-unit; "
        "miss_angle and rx,ry,rz in rad); rows not reached are named on stderr and kept in the file.",
    )
    cp.add_argument("run", help="run directory written by calibrate")
    cp.add_argument(
        "targets", help="CSV with x,y,z [m] and/or q1..qN [rad], optional rx,ry,rz (the measurement file format)"
    )
    cp.add_argument(
        "--out",
        required=True,
        help="CSV to write: the commands q1..qN, the file's joints q1_program..qN_program, the targets, station, "
        "probe, extra columns, sx,sy,sz, extrapolation, model (full, geometric or physical: which model commanded "
        "the row), miss, miss_angle [rad] (6-D), status",
    )
    cp.add_argument("--start", default=None, help="CSV with q1..qN: start joints per row (x,y,z-only targets)")
    cp.add_argument(
        "--payload",
        type=NONNEG,
        default=None,
        metavar="KG",
        help="the program's payload at the flange (default: the targets' payload column, else 0): the calibrated "
        "compliance carries it",
    )
    cp.add_argument(
        "--position-only",
        action="store_true",
        help="solve positions only (the tool free to turn), even with orientation targets (rx,ry,rz or program "
        "joints) and a run that fitted the probe's orientation",
    )
    cp.add_argument(
        "--orientation-weight",
        dest="weight",
        type=_number("positive"),  # 0, a negative, inf or nan weight is no solve: argparse's exit 2 names the option
        default=0.1,
        metavar="M_PER_RAD",
        help="in a 6-D solve, the length [m] an orientation error of 1 rad weighs as (default 0.1: as a point 100 mm "
        "from the probe moves); it decides only where position and orientation cannot both be met",
    )
    cp.add_argument(
        "--station",
        default=None,
        help="a run calibrated from several instrument stations: the station whose frame the targets are in, for "
        "rows without a station column (default the first; a row whose column names another is refused)",
    )
    cp.add_argument(
        "--probe",
        default=None,
        help="a run with several probes: the probe to put on the targets, for rows without a probe column (default "
        "the first)",
    )
    _add_force(cp)
    _add_units(cp)
    _add_common(cp)

    st = sub.add_parser(
        "station",
        help="re-station a calibrated run from a few points measured at a new instrument placement",
        description="Fit the instrument pose (and with --tool the lever arm) of a calibrated run to three or more "
        "points measured from a new placement of the instrument, the robot's calibration unchanged, and write a "
        "run directory that predict and compensate use at the new placement. Its report.json holds a station "
        "block: the new pose, its standard deviations and covariance, the points' residuals and leave-one-out "
        "errors, a chi-square test against the run's predicted error, and the placement's predicted effect on "
        "accuracy over poses like the points (their joint ranges, within the calibrated region). The points' station "
        "column may name the new placement (one name, new or one of the run's): the re-stationed run keeps that name.",
    )
    st.add_argument("run", help="run directory written by calibrate (or by an earlier station)")
    st.add_argument("points", help="measurement file with q1..qN and x,y,z (optional sx,sy,sz) of three or more points")
    st.add_argument("--out", required=True, help="run directory to write; " + REPLACED_HELP)
    st.add_argument(
        "--tool",
        action="store_true",
        help="fit the lever arm too (another tool or probe than the run's; without it, a changed tool is tested and "
        "fitted where the points fit worse than the run predicts and as predicted with a new lever arm; needs four "
        "or more points whose tool "
        "orientations differ; refused on a run of several probes, whose lever arms are kept)",
    )
    st.add_argument(
        "--probe",
        default=None,
        help="a run with several probes: the probe all the points were measured with (default: the points' probe "
        "column, row by row, else the run's first); refused on a run of one probe. A run of several stations is "
        "re-stationed as one placement (named after the points' station column where they have one: predict then "
        "refuses rows of another station); every probe keeps its lever arm; a learned correction per station and "
        "probe does not apply there",
    )
    _add_units(st)
    _add_common(st)

    pl = sub.add_parser(
        "plan",
        help="choose the poses to measure: the K that best serve the calibration method (default: the default "
        "method's design; --method kinematic for a geometric calibration)",
        description="Choose K poses from candidates (a file of joint configurations, or sampled within the joint "
        "limits where the tracker sees the probe) by a greedy I-optimal (or D-optimal) criterion on the "
        "identifiable geometric, instrument and lever-arm parameters, a share of them at the edges of the region. "
        "Writes OUT (q1..qN, a measurement file without positions) and next to it OUT's name with .plan.json and "
        ".plan.md: the predicted "
        "parameter sigmas, the predicted held-out error for K (and for K random candidates) and a curve of "
        "predicted error against K.",
    )
    pl.add_argument(
        "--robot",
        default=None,
        help="built-in name (ur5, ur10, panda, ...), a URDF file or a DH YAML file (default: the --run's robot)",
    )
    pl.add_argument("--base-link", default=None, help="URDF: first link of the chain (default: the root)")
    pl.add_argument("--tip-link", default=None, help="URDF: last link of the chain (default: the only deepest leaf)")
    pl.add_argument(
        "--run",
        default=None,
        help="run directory written by calibrate: plan with its calibrated model, instrument pose, lever arm, "
        "stochastic model and variance factor",
    )
    pl.add_argument(
        "--station",
        default=None,
        help="a --run calibrated from several stations: plan for this one's placement (default the first)",
    )
    pl.add_argument(
        "--probe", default=None, help="a --run with several probes: plan for this one's lever arm (default the first)"
    )
    pl.add_argument("--candidates", default=None, help="file with q1..qN per row (other columns ignored)")
    pl.add_argument(
        "--work",
        default=None,
        help="file with q1..qN of the poses the robot will work at (other columns ignored): the spread picks follow "
        "their density instead of the candidates' (the prediction stays over the candidates)",
    )
    pl.add_argument("--n", type=_count, required=True, help="poses to choose (K)")
    pl.add_argument("--out", required=True, help="CSV to write: q1..qN [rad] of the chosen poses")
    pl.add_argument(
        "--pool", type=_count, default=10_000, help="candidates to sample without --candidates (default 10000)"
    )
    pl.add_argument("--seed", type=_seed, default=0, help="seed of the sampled candidates and the random reference")
    pl.add_argument(
        "--criterion",
        choices=("I", "D"),
        default="I",
        help="I (default): the least mean position variance over the candidates; D: the largest determinant of "
        "the parameters' information",
    )
    pl.add_argument(
        "--method",
        default=None,
        choices=METHOD_CHOICES,
        help="the method the poses will be calibrated with (default: the --run's, else auto). kinematic: the "
        "criterion's design with half the picks spread; any other method ends in a learned correction, which needs "
        "poses where the robot works: the first 30 picks the criterion's, then the candidates' density",
    )
    pl.add_argument(
        "--edge-share",
        type=_number("nonnegative", 0.5),
        default=None,
        help="share of the picks made at the edges of the region (default 0.1 for kinematic, else 0.02)",
    )
    pl.add_argument(
        "--learned-share",
        type=_number("nonnegative", 0.5),
        default=0.0,
        help="with a --run whose learned correction has a predictive sigma (a GP): share of the picks made where it "
        "is least certain (default 0: on the real UR10 they made a second campaign worse)",
    )
    pl.add_argument(
        "--spread-share",
        type=_number("nonnegative", 1.0),
        default=None,
        help="share of the picks that follow the candidates' spread (kernel herding) instead of the criterion: they "
        "guard the geometry against the robot's non-geometric error (default 0.5 for kinematic, else 1 after the "
        "first 30 picks; 0: the criterion alone)",
    )
    pl.add_argument(
        "--tracker",
        type=_tool,
        default=None,
        help="X,Y,Z [mm]: the tracker's position in the robot base frame, for the line of sight of sampled "
        "candidates (default: the --run's, else 2500,0,200)",
    )
    pl.add_argument(
        "--tool",
        type=_tool,
        default=None,
        help="X,Y,Z [mm]: the probe's lever arm (default: the --run's, else 0,0,100)",
    )
    pl.add_argument(
        "--tracker-noise",
        type=TRACKER_UM,
        default=None,
        help="tracker sigma per axis [um] (default: the run's, else 15)",
    )
    pl.add_argument(
        "--joint-noise", type=JOINT_DEG, default=None, help="joint sigma [deg] (default: the run's, else 0.0005)"
    )
    _add_force(pl)
    _add_units(pl)
    _add_common(pl)

    fl = sub.add_parser(
        "fleet",
        help="calibrate a fleet: one calibration (or re-check from a prior run) per manifest line, in parallel on Ray",
        description="Run one calibration per line of MANIFEST (a CSV with the columns name,data,robot and optionally "
        "method,prior; paths relative to its folder) as independent tasks on Ray (pip install torchcal[fleet]; "
        "without it the tasks run one after another): line NAME's run in OUT/NAME/, a summary of every robot's "
        "held-out error, what moved since its prior and which need a new calibration in OUT/report.json and "
        "report.md. A failed task is reported as its line's and the others go on.",
    )
    fl.add_argument("manifest", help="CSV: name,data,robot[,method][,prior], a header row first")
    fl.add_argument("--out", required=True, help="fleet directory to write. " + OUT_REPLACED)
    fl.add_argument("--workers", type=_count, default=None, help="CPUs of the local Ray instance (default: all)")
    fl.add_argument(
        "--address",
        default=None,
        help="an existing Ray cluster instead of a private local instance: HOST:PORT, the head's address as "
        "'ray start --head' prints it (port 6379 by default); auto, the cluster started on this machine; or "
        "ray://HOST:10001, the head's Ray Client server where it runs one. A head with token authentication needs "
        "RAY_AUTH_MODE=token and its token (RAY_AUTH_TOKEN or ~/.ray/auth_token) in this environment",
    )
    _add_common(fl)

    _add_import_export(sub)

    d = sub.add_parser(
        "demo",
        help="run the main job end to end on built-in simulated data",
        description="Simulate a UR5 campaign with effects the nominal model lacks (joint-2 compliance "
        "and a smooth field), close the loop and print the error before and after every step.",
    )
    d.add_argument("--out", default="runs/demo", help="output directory (default runs/demo). " + OUT_REPLACED)
    d.add_argument("--seed", type=_seed, default=0, help="random seed, 0 to 2**63 - 1 (default 0)")
    _add_common(d)
    return parser


def calibration_module():
    """The module with ``calibrate``, ``Options``, ``min_poses``, ``DEFAULT_METHOD`` (one place to change)."""
    from torchcal import pipeline as C

    return C


def _robot_input(spec: str) -> list[str]:
    """The robot description as an input file when ``spec`` is a path (built-in names are not inputs)."""
    return [spec] if Path(spec).is_file() else []


def _robot_key(name: str) -> str:
    n = Path(str(name).strip()).name.lower()
    for ext in (".urdf", ".yaml", ".yml"):
        if n.endswith(ext):
            n = n[: -len(ext)]
    return n


def check_header_robot(data, spec: str, robot, described: str) -> None:
    """Refuse a file whose ``# robot:`` line names another robot than ``--robot``.

    A mismatch would otherwise be "calibrated" away as huge geometric corrections. Names are compared
    without directory, extension and case (``ur5``, ``robots/ur5.urdf`` and a URDF named ``UR5`` agree).

    Args:
        data: the measurements (``data.meta['robot']`` is the file's line).
        spec: the robot as given (built-in name or file path); robot: the loaded robot.
        described: how the message names it, e.g. ``--robot ur5``.
    """
    from torchcal.errors import MeasurementFileError

    named = data.meta.get("robot")
    if not named:
        return
    ours = {_robot_key(spec), _robot_key(robot.name)}
    if _robot_key(named) not in ours:
        raise MeasurementFileError(
            data.source,
            f"the file's '# robot: {named}' line names another robot than {described} ('{robot.name}')",
            hint="pass the robot the data were measured with, or correct the '# robot:' "
            "line if the name differs but the robot is the same",
        )


def _reading(args, robot) -> dict:
    """The keywords of :func:`~torchcal.data.read_measurements` for a file of ``robot``'s joints in the units of
    ``--length-unit`` / ``--angle-unit``."""
    return dict(
        dof=robot.dof,
        joint_limits=robot.limits,
        length_unit=args.length_unit,
        angle_unit=args.angle_unit,
        robot_name=robot.name,
        joint_types=robot.joint_types,
    )


def _same(v):
    return v


def _mm(v):
    return None if v is None else v * 1e-3


#: ``calibrate``'s flags (argparse dest) -> the option each sets (its flat name, torchcal.pipeline.options.FLAGS)
#: and the conversion from the flag's unit to SI: one flag, one field
CALIBRATE_FLAGS = {
    "seed": ("seed", _same),
    "holdout": ("holdout", _same),
    "tracker_noise": ("sigma_tracker", lambda um: um * 1e-6),
    "orientation_noise": ("sigma_orientation", lambda deg: None if deg is None else math.radians(deg)),
    "joint_noise": ("sigma_joint", math.radians),
    "engine": ("engine", _same),
    "device": ("device", _same),
    "refit": ("refit", _same),
    "max_joint_error": ("max_joint_error", _mm),
    "tool": ("tool", _same),  # its argument type gives metres
    "tool_sigma": ("tool_sigma", _mm),
}


def cmd_calibrate(args) -> int:
    C = calibration_module()
    from torchcal.data import read_measurements
    from torchcal.report.rundir import write_run
    from torchcal.robot import load_robot
    from torchcal.robot.load import calibrated_flange

    inputs = [args.data, *_robot_input(args.robot), *([args.prior] if args.prior else [])]
    out = check_out_dir(args.out, inputs=inputs)  # before any fitting: refuse, touching nothing; resolved once
    # a run's robot_calibrated.urdf: the chain to calibrate ends at the flange, not at the earlier run's probe
    tip_link = args.tip_link or calibrated_flange(args.robot)
    robot = load_robot(args.robot, base_link=args.base_link, tip_link=tip_link)
    opts = C.Options.of(
        **{field: convert(getattr(args, dest)) for dest, (field, convert) in CALIBRATE_FLAGS.items()},
        **({} if args.method is None else {"method": args.method}),
        **({} if args.rank_tol is None else {"rank_tol": args.rank_tol}),
    )
    prior = None
    if args.prior:
        from torchcal.use.rundir import check_prior_robot, load_prior

        prior = load_prior(args.prior)
        check_prior_robot(args.prior, robot, args.robot)
    data = read_measurements(
        args.data,
        require_positions=True,
        min_poses=C.MIN_PRIOR_POSES if prior is not None else C.min_poses(robot, opts.split.holdout),
        purpose=f"a calibration from the prior run {args.prior}"
        if prior is not None
        else f"a {opts.method} calibration of '{robot.name}'",
        **_reading(args, robot),
    )
    check_header_robot(data, args.robot, robot, f"--robot {args.robot}")
    if prior is None:  # an update from a few rows is judged on a separate check file, not on one or two rows
        C.check_holdout(data.n, opts.split.holdout)
    run = C.calibrate(robot, data, opts, robot_spec=args.robot, prior=prior)
    out = write_run(run, out, inputs=inputs)
    ida = run.identifiability
    for line in ida.combinations() if ida is not None else []:  # a weak combination: what a user must not miss
        _console.info(f"torchcal calibrate: warning: {line}")
    _warn_global_test(json.loads((out / "report.json").read_text(encoding="utf-8"))["global_test"])
    st = {s.name: s for s in run.stages}
    _console.info(
        f"held-out RMSE: nominal {st['nominal'].rmse * 1e3:.4f} mm, geometric "
        f"{st['geometric'].rmse * 1e3:.4f} mm, final {run.stages[-1].rmse * 1e3:.4f} mm"
    )
    for e in run.effects_report:
        _console.info("effect found: " + _effect_line(e))
    _console.info(f"wrote {out / 'report.json'} and {out / 'report.md'}")
    return 0


#: how many times its threshold a failed global test must be to be said on stderr (report.md always says it): a
#: real campaign fails it by far (variance factors of 100 to 4000: every real model leaves more than the instrument's
#: noise), so what is said is what the test found, and a warning only where it reads as a mistake
GLOBAL_TEST_WARN = 100.0


def _warn_global_test(gt: dict) -> None:
    """Say on stderr what a failed global test found (report.json ``global_test``, :mod:`torchcal.diagnose.noise`):
    a warning with the unit and description hint where the kinematic calibration leaves too large a share of the arm's
    reach; where it failed by far otherwise, a note of what the model leaves against the instrument's noise."""
    from torchcal.report.markdown import global_test_finding

    if gt.get("passed", True):
        return
    stat, thr = float(gt["statistic"]), float(gt["threshold"])
    head = f"variance factor {stat:.4g} against {thr:.3g} ({stat / thr:.0f} x)"
    if gt.get("reading") == "mistake":
        _console.info(f"torchcal calibrate: warning: the global test failed by far: {head}. {global_test_finding(gt)}")
    elif stat > GLOBAL_TEST_WARN * thr:
        from torchcal.diagnose.noise import NoiseLevel

        noise = NoiseLevel(gt["noise"]["sigma_m"], gt["noise"]["source"], gt["noise"]["dof"])
        _console.info(
            f"torchcal calibrate: note: the global test fails ({head}): the model leaves {gt['unexplained_mm']:.3g} mm "
            f"unexplained (held-out RMSE), {gt['times_noise'] or float('nan'):.3g} times the noise level "
            f"({noise.words()}): see report.md's effects and unexplained structure"
        )


#: how many rows outside the calibrated region predict and compensate name on stderr before counting the rest
MAX_OUTSIDE_LINES = 20
#: how far beyond the calibrated region a reading must lie to be warned about, in joint reading noises (the default
#: ``sigma_joint``, 0.0005 deg: 1.7e-4 rad or m): a pose 2.5e-7 rad beyond, or compensate's own solution 2-6e-5 rad
#: beyond a training pose, is the same pose within the readings' noise
OUTSIDE_TOL_SIGMAS = 20.0


def outside_rows(model, q) -> list[tuple[int, str]]:
    """The rows of ``q (N, dof)`` worth a warning, with why: a joint beyond the range it covered in the calibration
    by more than the tolerance (:data:`OUTSIDE_TOL_SIGMAS`), or a joint the calibration held still (a range within
    the tolerance) moved away from where it was held."""
    from torchcal.use.rundir import tool_axis_beyond

    turned = tool_axis_beyond(model, q) if getattr(model, "tool_cone", None) is not None else None
    if model.region is None and turned is None:
        return []
    if model.region is None:
        return [(i, _turned_why(float(turned[i]))) for i in range(len(q)) if float(turned[i]) > TURNED_TOL]
    tol = OUTSIDE_TOL_SIGMAS * SIGMA_JOINT
    lo, hi = (x.detach().cpu() for x in model.region)
    beyond = torch.maximum(lo - q.detach().cpu(), q.detach().cpu() - hi).clamp(min=0)  # (N, dof)
    held = (hi - lo) <= tol
    out = []
    for i in range(beyond.shape[0]):
        far = [k for k in range(beyond.shape[1]) if float(beyond[i, k]) > tol]
        if not far:
            if turned is not None and float(turned[i]) > TURNED_TOL:
                out.append((i, _turned_why(float(turned[i]))))
            continue
        k = max(far, key=lambda j: float(beyond[i, j]))
        unit = "m" if model.robot.joint_types[k] == "prismatic" else "rad"
        if bool(held[k]):
            why = (
                f"q{k + 1} moved {float(beyond[i, k]):.3g} {unit} from where the calibration held it (it never moved "
                "there)"
            )
        else:
            why = f"the pose lies {float(beyond[i, k]):.3g} {unit} beyond the calibrated region (q{k + 1})"
        out.append((i, why))
    return out


#: how far [rad] a tool axis must lie beyond the cone the calibration's tool axes covered to be warned about (0.1 deg)
TURNED_TOL = math.radians(0.1)


def _turned_why(angle: float) -> str:
    return (
        f"the tool axis lies {math.degrees(angle):.3g} deg beyond the orientations the calibration saw (a tool turned "
        "further over than any calibration pose)"
    )


def warn_outside(path, lines, model, q, what: str) -> None:
    """Warn on stderr (not under ``--quiet``), one line per row (the first ``MAX_OUTSIDE_LINES``, then a count), for
    the rows of :func:`outside_rows`."""
    rows = outside_rows(model, q)
    for i, why in rows[:MAX_OUTSIDE_LINES]:
        line = lines[i] if lines is not None and i < len(lines) else i + 1
        _console.info(f"torchcal: warning: {path}: line {line}: {why}" + (f"; {what}" if what else ""))
    if len(rows) > MAX_OUTSIDE_LINES:
        _console.info(
            f"torchcal: warning: {path}: {len(rows) - MAX_OUTSIDE_LINES} more rows outside the calibrated region "
            "(the extrapolation column names them)"
        )


def _one_torch_thread(command):
    """Run a command that uses a run (``predict``, ``compensate``, ``plan``) with one torch thread.

    Their work is a long series of small kernels (a model evaluated per parameter step, row blocks of a few hundred
    rows, 3 x 3 factors per candidate): a second thread shortens none of them, and where other work shares the cores,
    each kernel waits for the slowest member of torch's thread team, spinning meanwhile (docs/benchmarks.md, *Speed of
    predict, compensate and plan*). The results are the same to rounding (a thread count may change the order of a
    sum).
    """

    @functools.wraps(command)
    def run(args) -> int:
        with torch_threads(1):
            return command(args)

    return run


def _has_load(data, meta: dict) -> bool:
    """Whether predict's rows carry load columns or the run was fitted with them."""
    load = meta.get("load") if isinstance(meta.get("load"), dict) else {}
    return (
        data.payload is not None or data.tau is not None or bool(load.get("payload_column")) or bool(load.get("tau_Nm"))
    )


def _prediction_rows(args, model, meta):
    """``predict``'s rows: DATA read for the run's robot (text columns beside the numbers ignored), its header's robot
    and its stations checked against the run's."""
    from torchcal.data import read_measurements
    from torchcal.use.rundir import check_placement

    robot = model.robot
    data = read_measurements(
        args.data,
        dof=robot.dof,
        joint_limits=robot.limits,
        length_unit=args.length_unit,
        angle_unit=args.angle_unit,
        require_positions=False,
        robot_name=robot.name,
        joint_types=robot.joint_types,
        text_columns=True,  # notes beside the numbers ('stat: ok') were refused as 'not a number'
    )
    check_header_robot(data, meta["robot_file"], robot, f"the run's robot {meta['robot_file']}")
    check_placement(meta, data)  # a re-stationed run: rows of another station are refused
    return data


def _prediction_trust(args, model, meta, data):
    """How far to trust each row (on the CPU, before the model moves to --device): the standard deviation of a new
    measurement minus the prediction, how far the pose lies outside the calibrated region, and which model predicts
    it (beyond the region, the one with the smaller sigma); a load the run was not fitted at is flagged, its sigma and
    extrapolation grown (:mod:`torchcal.use.conditions`). Returns ``(trust, sigma, extrapolation, load conditions)``."""
    from torchcal.effects import Context
    from torchcal.use.conditions import load_conditions, with_load_sigma
    from torchcal.use.rundir import row_trust

    trajectory = bool(meta.get("trajectory")) and data.t is not None
    rt = row_trust(args.run, model, meta, Context.from_measurements(data, trajectory=trajectory))
    sigma, ext = rt.sigma, rt.extrapolation
    lc = load_conditions(model, meta, data, str(args.data))
    if lc.note is not None:
        _console.info(lc.note)
        sigma, ext = with_load_sigma(sigma, lc.sigma), torch.maximum(ext, lc.extrapolation.to(ext))
    return rt, sigma, ext, lc


@_one_torch_thread
def cmd_predict(args) -> int:
    from dataclasses import replace

    from torchcal.data import write_measurements
    from torchcal.data.load import is_load_column
    from torchcal.use.conditions import CONDITIONS
    from torchcal.use.rundir import MODEL_NAMES, load_model, predict_orientation, predict_with, rows_of

    out_file = check_out_file(args.out, inputs=[args.data, args.run], force=args.force)
    device = resolve_device(args.device)  # before any work: an absent CUDA device is a usage error
    model, meta = load_model(args.run)
    data = _prediction_rows(args, model, meta)
    labels = {k: getattr(data, k) for k in ("station", "station_names", "probe", "probe_names")}  # kept in the output
    data = rows_of(model, data)  # each row's station and probe in the run's order (absent: the first)
    rt, sigma, ext, lc = _prediction_trust(args, model, meta, data)
    p = predict_with(model, meta, data, device=device)
    if rt.geometric is not None and bool(rt.which.any()):
        rows = torch.nonzero(rt.which).flatten()
        p[rows] = predict_with(rt.geometric, meta, data.subset(rows), device=device)
    if rt.note is not None:
        _console.info(rt.note)
    if not bool(torch.isfinite(p).all()):
        raise OptionError(
            f"{args.run}: the run's model predicts non-finite positions for {args.data}; "
            "the run directory is damaged or the fit diverged"
        )
    if sigma is None:
        _console.info(f"{args.run}: the run has no parameter covariance or predictive model; no sx, sy, sz columns")
    # rx, ry, rz where the run fitted a 6-D probe's orientation (no srx, sry, srz: their covariance is not carried)
    r = predict_orientation(model, meta, data)
    out = replace(
        data,
        p=p,
        sigma=sigma,
        temperature=None,
        extra={
            **{k: v for k, v in data.extra.items() if is_load_column(k)},  # the rows' load, kept
            "extrapolation": ext,
            "model": rt.which.to(torch.float64),
            # where the rows carry a load (or the run was fitted at one): which lie beyond its training load
            **({"conditions": lc.beyond.to(torch.float64)} if _has_load(data, meta) else {}),
        },
        meta={"predicted_by": str(args.run)},
        r=r,
        sigma_r=None,
        **labels,
    )
    fade = "the learned corrections fade to the geometry there" if model.has_learned else ""
    warn_outside(args.data, data.lines, model, data.q, fade)
    out_file.parent.mkdir(parents=True, exist_ok=True)
    write_measurements(
        out_file, out, written_by="torchcal predict", labels={"model": MODEL_NAMES, "conditions": CONDITIONS}
    )
    _console.info(f"wrote {len(p)} predictions to {args.out}")
    return 0


#: compensate's column ``model``: the run's model, its kinematic calibration (beyond the region where the model's
#: sigma is far above that one's), or the geometry and physical effects alone (beyond the region otherwise)
COMPENSATE_MODELS = ("full", "geometric", "physical")


def _compensate_trust(args, model, meta, res, ctx, plain, resolve):
    """compensate's ``sx, sy, sz`` and ``model`` per row: rows beyond the region where the run's model's sigma is far
    above its kinematic calibration's are solved again with that (``resolve(geometric, rows)``, in place in
    ``res``), with its sigma at the new commands."""
    from dataclasses import replace

    from torchcal.use.rundir import row_trust

    rt = row_trust(args.run, model, meta, ctx)
    which = torch.where(plain.cpu(), 2, 0)
    if rt.geometric is None or not bool(rt.which.any()):
        return rt.sigma, which
    rows = torch.nonzero(rt.which).flatten()
    resolve(rt.geometric, rows.to(res.q.device))
    sigma = rt.sigma.clone()
    sub = ctx.subset(rows.to(ctx.q.device))
    sigma[rows] = rt.geometric_sigma(replace(sub, q=res.q[rows.to(res.q.device)]))  # at the new commands
    which[rows] = 1
    return sigma, which


def _geometric_resolver(res, station, probe, targets_of, context, weight):
    """``(geometric, rows) ->`` those rows of ``res`` solved again, in place, with the run's kinematic calibration
    ``geometric`` in each row's own station's frame with its own probe."""
    from torchcal.use.compensate import solve_rows_with
    from torchcal.use.rundir import at_station

    def resolve(geometric, rows):
        robot, n = geometric.robot, len(res.q)
        for s, p in sorted(set(zip(station[rows].tolist(), probe[rows].tolist(), strict=True))):
            sel = rows[(station[rows] == s) & (probe[rows] == p)]
            names = (robot.stations[s] if robot.stations else None, robot.probes[p] if robot.probes else None)
            geo, *_ = at_station(geometric, *names)
            pos, rot = targets_of(geo, sel)
            targets = torch.zeros(n, 3, dtype=pos.dtype, device=pos.device)
            targets[sel] = pos
            kw = {"orientation_weight": weight}
            if rot is not None:  # full-length, as the rows' context: solve_rows_with takes the rows of both
                kw["orientations"] = torch.eye(3, dtype=rot.dtype, device=rot.device).repeat(n, 1, 1)
                kw["orientations"][sel] = rot
            solve_rows_with(geo, res, sel, targets, context=context, **kw)

    return resolve


def _program_load(args, data, model) -> dict:
    """The program's load per row for the context of the compensation: its payload [kg] (``--payload KG``, else the
    targets' ``payload`` column) and the torques its poses hold (the targets' ``tau`` columns), which the run's
    compliance carries. A run whose compliance reads measured torques needs them."""
    from torchcal.effects import TorqueCompliance

    if data.tau is None and any(isinstance(e, TorqueCompliance) for e in model.effects):
        raise TorchcalError(
            f"{args.targets}: the run's compliance reads the measured joint torques: give the targets the columns "
            f"tau1..tau{model.robot.dof} (N m), the torques the program's poses hold"
        )
    payload = _payload_of(args, data)
    return {**({} if payload is None else {"payload": payload}), **({} if data.tau is None else {"tau": data.tau})}


def _payload_of(args, data) -> torch.Tensor | None:
    """``--payload KG`` for every row, else the targets' ``payload`` column, else None (0 kg)."""
    if args.payload is not None:
        return torch.full((data.n,), float(args.payload), dtype=torch.float64, device=data.q.device)
    return data.payload


@_one_torch_thread
def cmd_compensate(args) -> int:
    from torchcal.data import read_measurements
    from torchcal.use.compensate import Status, compensate_groups, orientation_mode, row_groups
    from torchcal.use.rundir import at_station, check_placement, load_model, own_names

    out_file = check_out_file(
        args.out, inputs=[args.targets, args.run] + ([args.start] if args.start else []), force=args.force
    )
    model, meta = load_model(args.run)
    robot = model.robot
    kw = dict(require_positions=False, **_reading(args, robot))
    data = read_measurements(args.targets, require_joints=False, **kw)
    check_placement(meta, data)  # a re-stationed run: rows of another station are refused
    # each row in its own station's frame with its own probe (the columns, else --station / --probe, else the first)
    station, probe = row_groups(model, data, *own_names(meta, args.station, args.probe))
    q_start = data.q if data.dof > 0 else None
    if args.start is not None:
        start = read_measurements(args.start, **kw)
        if start.n != data.n:
            raise TorchcalError(
                f"{args.start}: {start.n} start rows for {data.n} targets in {args.targets}; "
                "give one start row per target"
            )
        q_start = start.q
    six_d, mode = orientation_mode(robot, data, args.position_only)
    if data.r is not None and not six_d:
        _console.info(f"torchcal: warning: {args.targets}: the rx,ry,rz columns are not used: {mode}")
    _console.info(f"compensate: {mode}")
    trajectory = bool(meta.get("trajectory")) and data.t is not None
    context = {
        "t": data.t,
        "temperature": data.temperature,
        "trajectory": trajectory,
        **_program_load(args, data, model),
    }
    targets_of = _compensation_targets(data, six_d)
    res, ext, plain = compensate_groups(
        model, station, probe, targets_of, q_start, at=at_station, context=context, orientation_weight=args.weight
    )
    resolve = _geometric_resolver(res, station, probe, targets_of, context, args.weight)
    _write_compensation(args, out_file, (model, meta), data, (station, probe), res, (plain, resolve), mode)
    alone = "commanded by the geometry and physical effects alone" if model.has_learned else ""
    warn_outside(args.targets, data.lines, model, res.q, alone)
    for i in [i for i, s in enumerate(res.status) if s is not Status.CONVERGED]:
        turn = "" if res.miss_angle is None else f" and {math.degrees(float(res.miss_angle[i])):.3g} deg"
        if res.position_only is not None and bool(res.position_only[i]):
            turn += " (the full pose is not reached on this arm configuration: commanded for the position alone)"
        print(
            f"torchcal compensate: {args.targets}: line {data.lines[i]}: {res.status[i].value}, the model misses "
            f"the target by {float(res.miss[i]) * 1e3:.3g} mm{turn}",  # 4 decimals printed a 1e-9 mm miss as 0
            file=sys.stderr,
        )
    _console.info(
        f"wrote {data.n} joint commands to {args.out}: " + ", ".join(f"{v} {k}" for k, v in res.counts().items())
    )
    return 0


def _compensation_targets(data, six_d: bool):
    """``(model, rows) -> (positions, orientations or None)`` of a targets file, in the instrument frame of ``model``
    (the run at the rows' station and probe): the file's ``x,y,z`` (``rx,ry,rz``), or what a program's joints mean."""
    from torchcal.robot import transforms as tf
    from torchcal.use.compensate import program_orientations, program_targets

    def targets_of(at, rows):
        p = data.p[rows] if data.p is not None else program_targets(at, data.q[rows])
        if not six_d:
            return p, None
        return p, tf.so3_exp(data.r[rows]) if data.r is not None else program_orientations(at, data.q[rows])

    return targets_of


def _write_compensation(args, out_file, run, data, groups, res, plain_resolve, mode) -> None:
    """Write ``compensate``'s file in the targets file's units: the commands, the program's own joints beside them
    (``q1_program..``), the targets, labels, extra columns, trust columns, the misses and the status. Rows where
    the run's kinematic calibration is far surer are solved again with it first (:func:`_compensate_trust`)."""
    import dataclasses

    from torchcal.effects import Context
    from torchcal.use.compensate import file_units, write_joints

    (model, meta), (station, probe), (plain, resolve) = run, groups, plain_resolve
    # how far to trust each command: the predicted standard deviation of a measurement there, and which model
    rows = dict(station=station if model.robot.stations else None, probe=probe if model.robot.probes else None)
    load = dict(payload=_payload_of(args, data), tau=data.tau)
    ctx = Context(q=res.q, t=data.t, temperature=data.temperature, **load, **rows)
    sigma, which = _compensate_trust(args, model, meta, res, ctx, plain, resolve)
    joint, length = file_units(model.robot.joint_types, args.length_unit, args.angle_unit)
    extra = {f"q{k + 1}_program": data.q[:, k] * joint[k] for k in range(data.dof)}
    extra.update(data.extra)
    sigma, ext, conditions = _compensate_load(args, (model, meta), data, res.q, sigma)
    if load["payload"] is not None:  # the payload the commands were solved with (--payload wins over the column)
        extra["payload"] = load["payload"]
    if sigma is not None:
        extra.update(sx=sigma[:, 0] * length, sy=sigma[:, 1] * length, sz=sigma[:, 2] * length)
    extra["extrapolation"] = ext  # of the commands written
    extra["model"] = [COMPENSATE_MODELS[int(i)] for i in which.tolist()]
    if conditions is not None:
        extra["conditions"] = conditions
    write_joints(
        out_file,
        dataclasses.replace(res, q=res.q * joint, miss=res.miss * length),
        targets=None if data.p is None else data.p * length,
        t=data.t,
        temperature=data.temperature,
        labels=_row_labels(model, data, station, probe),
        extra=extra,
        meta={
            "compensated_by": str(args.run),
            "compensation": mode,
            "length_unit": args.length_unit,
            "angle_unit": args.angle_unit,
        },
        written_by="torchcal compensate",
    )


def _compensate_load(args, run, data, q, sigma):
    """The commands' load against the run's training load (:mod:`torchcal.use.conditions`): the sigma and
    extrapolation grown where it lies beyond, and the ``conditions`` column (None where neither the targets nor the
    run carry load columns)."""
    import dataclasses

    from torchcal.use.conditions import CONDITIONS, load_conditions, with_load_sigma

    model, meta = run
    ext = model.extrapolation(q)
    payload = _payload_of(args, data)
    extra = {k: v for k, v in data.extra.items() if k != "payload"}
    rows = dataclasses.replace(data, q=q, extra=extra if payload is None else {**extra, "payload": payload})
    lc = load_conditions(model, meta, rows, str(args.targets))
    if lc.note is not None:
        _console.info(lc.note)
        sigma, ext = with_load_sigma(sigma, lc.sigma), torch.maximum(ext, lc.extrapolation.to(ext))
    if not (_has_load(rows, meta) or args.payload is not None):
        return sigma, ext, None
    return sigma, ext, [CONDITIONS[int(b)] for b in lc.beyond.tolist()]


def _row_labels(model, data, station, probe) -> dict[str, list[str]]:
    """The ``station`` and ``probe`` columns to write back: each row's name where the run has several (the one the
    row was solved for), the file's own text where the run has one."""
    out = {}
    for key, index, known in (("station", station, model.robot.stations), ("probe", probe, model.robot.probes)):
        column, names = getattr(data, key), getattr(data, f"{key}_names")
        if known:
            out[key] = [known[i] for i in index.tolist()]
        elif column is not None:
            out[key] = [names[i] for i in column.tolist()]
    return out


def cmd_station(args) -> int:
    from torchcal.data import read_measurements
    from torchcal.report.station import write_station
    from torchcal.use.rundir import load_model
    from torchcal.use.station import restation

    run = Path(args.run)
    inputs = [args.points, run / "model.json", run / "model.pt"]
    out = check_out_dir(args.out, inputs=inputs)  # before any work: refuse, touching nothing
    model, meta = load_model(args.run)
    robot = model.robot
    data = read_measurements(
        args.points,
        require_positions=True,
        min_poses=4 if args.tool else 3,
        purpose="re-stationing the instrument pose" + (" and the lever arm" if args.tool else ""),
        **_reading(args, robot),
    )
    check_header_robot(data, meta["robot_file"], robot, f"the run's robot {meta['robot_file']}")
    restationed, meta, station = restation(args.run, data, tool=args.tool, probe=args.probe)
    out = write_station(args.run, restationed, meta, station, out, points_file=args.points, inputs=inputs)
    d = station.to_dict()
    acc = d["accuracy"]
    for w in station.warnings:
        print(_console.one_line(f"torchcal station: warning: {w}"), file=sys.stderr)
    _console.info(
        f"re-stationed on {d['n_points']} points: residual RMS {d['rmse_points_mm']:.4f} mm; placement sigma "
        f"{acc['placement_sigma_rms_mm']:.4f} mm RMS over the points' region, predicted error "
        f"{acc['predicted_rmse_mm']:.4f} mm"
        + (
            " (the placement sigma alone carries a parameter the run held at its prior, which the placement absorbs at "
            "these poses: together they cancel)"
            if acc["placement_sigma_rms_mm"] > 2 * acc["predicted_rmse_mm"]
            else ""
        )
    )
    _console.info(f"wrote {out}")
    return 0


def _plan_side_file(path: str, inputs: list, force: bool) -> Path:
    """``plan``'s summary next to its poses: an earlier plan's JSON (``"written_by": "torchcal plan"``, JSON has no
    comment line for the usual mark) is replaced like a marked file; anything else as :func:`check_out_file` says."""
    p = Path(path)
    if p.suffix == ".json" and p.is_file() and not p.is_symlink():
        try:
            earlier = json.loads(p.read_text(encoding="utf-8")).get("written_by") == "torchcal plan"
        except (ValueError, OSError, AttributeError):
            earlier = False
        if earlier:
            return check_out_file(path, inputs=inputs, force=True)
    return check_out_file(path, inputs=inputs, force=force)


def _plan_run(args):
    """``plan --run``: the run's model (at ``--station`` / ``--probe``), robot file, method, noise, variance factor
    and scene (tracker position, lever arm)."""
    from torchcal.use.plan import scene_of
    from torchcal.use.rundir import load_model
    from torchcal.use.station import station_options

    model, meta = load_model(args.run)
    if args.robot is not None and _robot_key(args.robot) not in {
        _robot_key(meta["robot_file"]),
        _robot_key(model.robot.name),
    }:  # the run's model is what is planned for: another --robot would be ignored without a word
        raise OptionError(
            f"--robot {args.robot} is not the robot of the run {args.run} ({meta['robot_file']}); the plan is "
            "made for the run's calibrated robot: drop --robot, or plan for that robot without --run"
        )
    method = args.method or meta.get("method") or "auto"
    from torchcal.use.rundir import at_station, own_names

    station, probe = own_names(meta, args.station, args.probe)
    if model.robot.stations or model.robot.probes:  # plan for one placement and probe of a several-station run
        model, _, _ = at_station(model, station, probe)
    elif station is not None or probe is not None:
        raise OptionError("--station and --probe name one of a run's several stations or probes; this run has one")
    so = station_options(args.run)
    s0_sq = 1.0
    report = Path(args.run) / "report.json"
    if report.exists():
        s0 = json.loads(report.read_text(encoding="utf-8")).get("parameters", {}).get("sigma0_sq")
        s0_sq = float(s0) if isinstance(s0, (int, float)) and math.isfinite(s0) and s0 > 0 else 1.0
    tracker, lever = scene_of(model)
    return model, meta["robot_file"], method, so.sigma_tracker, so.sigma_joint, s0_sq, tracker, lever


@_one_torch_thread
def cmd_plan(args) -> int:
    from torchcal.data import Measurements, read_measurements, write_measurements
    from torchcal.effects import MeasurementModel
    from torchcal.use.plan import PlanOptions, distinct_poses, plan_poses, sample_candidates

    inputs = [p for p in (args.candidates, args.work, args.run) if p] + (_robot_input(args.robot) if args.robot else [])
    out_file = check_out_file(args.out, inputs=inputs, force=args.force)
    stem = out_file.with_suffix("")
    side = {ext: _plan_side_file(f"{stem}.plan.{ext}", inputs, args.force) for ext in ("json", "md")}
    if args.run is None and args.robot is None:
        raise OptionError("give --robot or --run (the robot to plan for)")
    sigma_tracker, sigma_joint, s0_sq = 15e-6, math.radians(0.0005), 1.0
    tracker = lever = None
    method = args.method or DEFAULT_METHOD.value
    if args.run is not None:
        model, robot_name, method, sigma_tracker, sigma_joint, s0_sq, tracker, lever = _plan_run(args)
    else:
        from torchcal.robot import load_robot

        model = MeasurementModel(load_robot(args.robot, base_link=args.base_link, tip_link=args.tip_link))
        robot_name = args.robot
    robot = model.robot
    if args.tracker is not None:
        tracker = torch.tensor(args.tracker, dtype=F64, device=robot.device)
    if args.tool is not None:
        lever = torch.tensor(args.tool, dtype=F64, device=robot.device)
    if args.tracker_noise is not None:
        sigma_tracker = args.tracker_noise * 1e-6
    if args.joint_noise is not None:
        sigma_joint = math.radians(args.joint_noise)
    work = None
    if args.work is not None:
        wd = read_measurements(args.work, require_positions=False, **_reading(args, robot))
        check_header_robot(wd, robot_name, robot, f"--robot {robot_name}")
        work = wd.q
    if args.candidates is not None:
        data = read_measurements(args.candidates, require_positions=False, **_reading(args, robot))
        check_header_robot(data, robot_name, robot, f"--robot {robot_name}")
        q = distinct_poses(data.q)  # a file of several probes has a row per probe and pose: a plan chooses poses
        if len(q) < data.n:
            _console.info(f"plan: {data.n - len(q)} candidate rows repeat another row's joints: each pose counted once")
        source = args.candidates
    else:
        region = model.region if args.run is not None else None  # a run: where it was calibrated
        within = " within the run's calibrated region" if region is not None else ""
        _console.info(f"sampling {args.pool} candidate poses the tracker sees{within} (seed {args.seed})")
        q = sample_candidates(model, args.pool, args.seed, tracker, lever, need=args.n, region=region)
        source = f"{len(q)} sampled{within} (seed {args.seed})"
    if args.n > len(q):
        raise OptionError(f"--n {args.n} is more than the {len(q)} candidates")
    opts = PlanOptions.for_method(
        method,
        args.n,
        criterion=args.criterion,
        edge_share=args.edge_share,
        learned_share=args.learned_share,
        spread_share=args.spread_share,
        sigma_tracker=sigma_tracker,
        sigma_joint=sigma_joint,
        s0_sq=s0_sq,
        seed=args.seed,
    )
    plan = plan_poses(model, q, opts, work)
    out_file.parent.mkdir(parents=True, exist_ok=True)
    meta_out = {"robot": Path(str(robot_name)).name, "planned_from": source}
    write_measurements(out_file, Measurements(q=plan.q.detach().cpu()), meta=meta_out, written_by="torchcal plan")
    summary = {"written_by": "torchcal plan", "poses": str(args.out), "candidates": source, **plan.to_dict()}
    side["json"].write_text(json.dumps(summary, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    side["md"].write_text("# written_by: torchcal plan\n\n" + plan.markdown(), encoding="utf-8")
    if not plan.identifies:  # written for inspection, but no accuracy is promised
        print(_console.one_line(f"torchcal plan: warning: {plan.degenerate_reason()}"), file=sys.stderr)
        _console.info(f"planned {args.n} of {len(q)} poses, no accuracy predicted; wrote {args.out}")
        return 0
    _console.info(
        f"planned {args.n} of {len(q)} poses: predicted held-out RMSE {plan.predicted_rmse * 1e3:.4f} mm "
        f"({args.n} random: "
        + ("not identified" if math.isnan(plan.random_rmse) else f"{plan.random_rmse * 1e3:.4f} mm")
        + f"); wrote {args.out}, {side['json'].name}, {side['md'].name}"
    )
    return 0


def cmd_fleet(args) -> int:
    from torchcal.fleet import print_progress, ray_available, run_fleet

    if args.address and args.workers:
        raise OptionError("--workers sizes a local Ray instance; a cluster at --address has its own")
    if not ray_available():
        _console.info(
            "torchcal fleet: Ray is not installed (pip install torchcal[fleet]): the calibrations run one after another"
        )
    fleet = run_fleet(args.manifest, args.out, workers=args.workers, address=args.address, progress=print_progress)
    d = fleet.to_dict()
    _console.info(
        f"{d['n_ok']} of {d['n_lines']} calibrated ({d['engine']}, {d['seconds']:.1f} s); needs a new calibration: "
        f"{', '.join(d['needs_calibration']) or 'none'}; wrote {Path(args.out) / 'report.json'}"
    )
    return 0


def cmd_convert(args) -> int:
    from torchcal.data import convert_ipa
    from torchcal.data.mapped import convert_mapped

    if (args.map is None) == (args.fmt is None):
        raise OptionError("convert takes one of --map MAP.yaml (a layout you describe) and --from FORMAT")
    if args.fmt is not None and len(args.inputs) != 1:
        raise OptionError(f"--from {args.fmt} converts one file, got {len(args.inputs)}")
    out_file = check_out_file(args.out, inputs=[*args.inputs, args.map], force=args.force)
    if args.map is not None:
        m = convert_mapped(args.map, args.inputs, out_file, written_by="torchcal convert")
        kinds = [k for k in ("station", "probe") if getattr(m, k) is not None]
        what = "".join(f", {len(getattr(m, f'{k}_names'))} {k}s" for k in kinds)
        cols = [
            f"q1..q{m.dof}",
            *(["x, y, z"] if m.p is not None else []),
            *(["rx, ry, rz"] if m.r is not None else []),
        ]
        cols += [*(["t"] if m.t is not None else []), *(["temperature"] if m.temperature is not None else [])]
        cols += [*m.extra, *kinds]
        _console.info(f"wrote {m.n} rows of {m.dof} joints{what} to {args.out}: columns {', '.join(cols)}")
        if m.r is not None:
            from torchcal.data.mapped import orientation_note

            _console.info(f"convert: note: {orientation_note(args.map)}")
        return 0
    m = convert_ipa(args.inputs[0], out_file, written_by="torchcal convert")
    _console.info(f"wrote {m.n} poses to {args.out} (series {m.meta.get('series', '?')})")
    return 0


def cmd_check_export(args) -> int:
    from torchcal.use.export import check_export

    c = check_export(args.run, args.file, geometry=args.geometry)
    expected = "" if c.expected_mm is None else f" (the run recorded {c.expected_mm:.4f} mm for this chain)"
    chain = {"run": "own", "standalone": "stand-alone", "cofitted": "co-fitted"}[c.which]
    print(
        f"{args.file} loaded to link '{c.tip}': largest difference to the run's {chain} chain {c.fk_gap_mm:.3g} mm "
        f"over {c.n} held-out poses; held-out RMSE with the run's instrument pose and lever arm "
        f"{c.rmse_mm:.4f} mm{expected}"
    )
    return 0


def cmd_export(args) -> int:
    from torchcal.use.export import export_run

    out_file = check_out_file(args.out, inputs=[args.run], force=args.force)
    run = Path(args.run).resolve()
    if run.is_dir() and Path(args.out).resolve().is_relative_to(run):
        # a file added to a run directory is not the run's: the run is written and replaced as a whole
        raise OptionError(
            f"--out {args.out} lies inside the run directory {args.run}, which torchcal writes and replaces as a "
            "whole: write the export beside it"
        )
    ex = export_run(args.run, args.format, out_file, geometry=args.geometry)
    _console.info(f"wrote the {args.format} file of {args.run} to {args.out}: {ex.summary}")
    loads = {"dh": (".yaml", ".yml"), "urdf": (".urdf",)}.get(args.format)
    if loads and Path(args.out).suffix.lower() not in loads:  # --robot tells a description's kind by its suffix
        _console.info(
            f"torchcal: note: --robot loads a {args.format} file by its name's ending ({' or '.join(loads)}); "
            f"rename {args.out} to load it back"
        )
    return 0


def _simulate(cfg):
    """``simulate(cfg)``, with the line-of-sight failure told in terms of the command's options."""
    from torchcal.sim import simulate

    try:
        return simulate(cfg)
    except RuntimeError as e:
        if "line-of-sight" not in str(e):
            raise
        raise OptionError(
            f"robot '{cfg.robot}': {e.args[0].split(';')[0]}: the simulated tracker cannot see the "
            "probe in enough poses. Check --robot, --base-link and --tip-link (the chain must end "
            "at the tool flange of an upright arm), or ask for fewer --poses/--samples"
        ) from None


def _load_levels(text: str) -> tuple[float, ...]:
    """``--payload-levels 0,5,10``: payloads [kg], at least one."""
    try:
        levels = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected payloads in kg separated by ',', e.g. 0,5,10; got {text!r}"
        ) from None
    if not all(math.isfinite(v) and v >= 0 for v in levels):
        raise argparse.ArgumentTypeError(f"payloads are masses >= 0 kg, got {text!r}")
    return levels


def _add_load_options(s) -> None:
    """simulate's loads: the payload of the training and test rows, levels, measured torques."""
    s.add_argument(
        "--payload", type=NONNEG, default=0.0, metavar="KG", help="payload at the probe of the training rows"
    )
    s.add_argument(
        "--test-payload", type=NONNEG, default=None, metavar="KG", help="payload of the test rows (default --payload)"
    )
    s.add_argument(
        "--payload-levels",
        type=_load_levels,
        default=None,
        metavar="KG,KG,..",
        help="rows (training and test) cycle over these payloads, e.g. 0,5,10",
    )
    s.add_argument(
        "--torques",
        action="store_true",
        help="write the joint torques the drives hold (tau1..tauN, N m) from the true static model plus noise",
    )
    s.add_argument(
        "--torque-noise", type=NONNEG, default=0.5, metavar="NM", help="standard deviation of --torques (default 0.5)"
    )


def cmd_simulate(args) -> int:
    from torchcal._outdir import replace_dir
    from torchcal.sim import EffectSpec, SimConfig, write_campaign

    inputs = _robot_input(args.robot)
    out = check_out_dir(args.out, inputs=inputs)
    if args.trajectory and args.train_samples >= args.samples:
        raise OptionError(
            f"--train-samples {args.train_samples} must be below --samples {args.samples} (the rest is the test phase)"
        )
    same = ("robot", "poses", "test_poses", "trajectory", "path", "samples", "train_samples", "seed")
    cfg = SimConfig(
        **{name: getattr(args, name) for name in same},
        sigma_tracker=args.tracker_noise * 1e-6,
        sigma_joint_deg=args.joint_noise,
        sigma_length=args.length_bias * 1e-3,
        sigma_angle_deg=args.angle_bias,
        effects=[EffectSpec.parse(e) for e in args.effect],
        write_sigma=not args.no_sigma,
        base_link=args.base_link,
        tip_link=args.tip_link,
        tool_axis_deg=args.fixed_tool_axis,
        orientation_sigma_deg=args.orientation,
        stations=args.stations,
        probes=args.probes,
        payload=args.payload,
        test_payload=args.test_payload,
        payload_levels=args.payload_levels,
        torques=args.torques,
        sigma_torque=args.torque_noise,
        narrow=args.narrow,
        narrow_width_deg=args.width_deg,
    )
    if args.width_deg != 1.0 and not args.narrow:
        raise OptionError("--width-deg needs --narrow JOINTS")
    what = "a trajectory" if cfg.trajectory else "static poses"
    _console.info(f"simulating {what} for '{cfg.robot}' (seed {cfg.seed})")
    campaign = _simulate(cfg)
    if args.length_unit == "mm":
        campaign = _to_mm(campaign)
    with replace_dir(out, kind="simulate", inputs=inputs) as tmp:
        names = {k: p.name for k, p in write_campaign(campaign, tmp).items()}
    for name in names.values():
        _console.info(f"wrote {Path(args.out) / name}")
    return 0


def _to_mm(campaign):
    """The campaign's lengths in millimetres: positions, their standard deviations and prismatic joints' readings."""
    from dataclasses import replace

    robot = campaign.model.robot
    linear = torch.tensor([k == "prismatic" for k in robot.joint_types], dtype=torch.bool, device=robot.device)

    def mm(m):
        return replace(
            m,
            q=torch.where(linear, m.q * 1000.0, m.q),
            p=m.p * 1000.0,
            sigma=None if m.sigma is None else m.sigma * 1000.0,
            meta={**m.meta, "length_unit": "mm"},
        )

    campaign.train, campaign.test = mm(campaign.train), mm(campaign.test)
    if campaign.turned is not None:
        campaign.turned = mm(campaign.turned)
    campaign.truth["files"]["length_unit"] = "mm"
    return campaign


DEMO_EFFECTS = ("compliance:2=60um", "field=0.05mm")


def cmd_demo(args) -> int:
    C = calibration_module()
    from torchcal._outdir import mark, replace_dir
    from torchcal.report.rundir import write_run_files
    from torchcal.sim import EffectSpec, SimConfig, write_campaign
    from torchcal.use.rundir import predict

    out = check_out_dir(args.out)
    cfg = SimConfig(
        robot="ur5", poses=800, test_poses=200, seed=args.seed, effects=[EffectSpec.parse(e) for e in DEMO_EFFECTS]
    )
    _console.info(
        "torchcal demo: a simulated UR5 laser-tracker campaign (800 + 200 poses) with biased geometry, "
        "joint-2 compliance (60 um RMS at the probe) and a smooth non-geometric field (0.05 mm RMS), "
        "neither of which the nominal model declares"
    )
    campaign = _simulate(cfg)
    run = C.calibrate(cfg.robot, campaign.train, C.Options(seed=args.seed))
    run_dir = out / "run"
    with replace_dir(out, kind="demo") as tmp:
        names = {k: p.name for k, p in write_campaign(campaign, tmp / "data").items()}
        (tmp / "run").mkdir()
        mark(tmp / "run", "calibrate")
        write_run_files(run, tmp / "run")
        p = predict(tmp / "run", campaign.test)
        test_rmse = float((p - campaign.test.p).norm(dim=-1).square().mean().sqrt())
        summary = {
            "data": {k: str(out / "data" / v) for k, v in names.items()},
            "run": str(run_dir),
            "simulated": list(DEMO_EFFECTS),
            "holdout_rmse_mm": {s.name: s.rmse * 1e3 for s in run.stages},
            "test_file_rmse_mm": test_rmse * 1e3,
            "stages": [s.name for s in run.stages],
            "effects": [{"kind": e["kind"], "joint": e["joint"]} for e in run.effects_report],
        }
        (tmp / "summary.json").write_text(json.dumps(summary, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    print(f"simulated, undeclared: {', '.join(DEMO_EFFECTS)}")
    print("model                                          held-out RMSE [mm]   max [mm]")
    labels = {
        "nominal": "nominal geometry (tracker, lever fitted)",
        "geometric": "after the kinematic calibration",
        "learned": "+ learned residual model",
    }
    for s in run.stages:
        label = labels.get(s.name, f"+ {s.name}")
        print(f"{label:47s} {s.rmse * 1e3:12.4f}   {float(s.holdout_errors.max()) * 1e3:9.4f}")
    print(f"{'final model on the separate test file':47s} {test_rmse * 1e3:12.4f}")
    print("effects found:" + ("" if run.effects_report else " none"))
    for e in run.effects_report:
        print("  " + _effect_line(e))
    # the path as the user gave --out (the run is written where it resolves to)
    print(f"report: {Path(args.out) / 'run' / 'report.md'}")
    return 0


def _effect_line(e: dict) -> str:
    """One found effect as the demo prints it: its name, its parameters with their units and the one p-value it was
    admitted on (named: the localisation's or the score test's, the same as report.md's)."""
    from torchcal.diagnose import named_p
    from torchcal.report.markdown import effect_params_words

    name = e["kind"] + (f" (joint {e['joint']})" if e["joint"] is not None else "")
    words = effect_params_words(e["params"])
    ev = e["evidence"]
    return name + (f": {words}" if words else "") + (f"; {named_p(ev)}" if "p_bonferroni" in ev else "")


COMMANDS = {
    "simulate": cmd_simulate,
    "calibrate": cmd_calibrate,
    "predict": cmd_predict,
    "convert": cmd_convert,
    "export": cmd_export,
    "check-export": cmd_check_export,
    "compensate": cmd_compensate,
    "station": cmd_station,
    "plan": cmd_plan,
    "fleet": cmd_fleet,
    "demo": cmd_demo,
}


def _warning_printer(command: str):
    """``warnings.showwarning`` for the command: one line naming the command, not the library's source file and
    line (a user cannot act on torch's internals; ``--debug`` tracebacks still show where)."""

    def show(message, category, filename, lineno, file=None, line=None):
        _console.info(f"torchcal {command}: warning: {category.__name__}: {message}")

    return show


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code (module docstring) instead of raising."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _console.set_quiet(getattr(args, "quiet", False))
    debug = bool(getattr(args, "debug", False))
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_printer(args.command)
            return COMMANDS[args.command](args)
    except TorchcalError as e:
        if debug:
            traceback.print_exc()
        print(f"torchcal {args.command}: error: {_console.one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torchcal {args.command}: interrupted; the output was left as it was", file=sys.stderr)
        return 130
    except OSError as e:
        if e.errno not in _REFUSED_ERRNOS:
            return _internal_error(args.command, e, debug)
        if debug:
            traceback.print_exc()
        # the output the user named: a failed write() carries no file name ("cannot write No space left on
        # device"), and a failed copy names its source (station named the input run's report.json)
        target = getattr(args, "out", None) or e.filename2 or e.filename
        where = f"{target}: " if target else ""
        print(
            f"torchcal {args.command}: error: cannot write {where}{e.strerror or e}; nothing was written "
            "(the output was left as it was)",
            file=sys.stderr,
        )
        return 2
    except Exception as e:  # the last line of defence: a summary, never a bare traceback
        return _internal_error(args.command, e, debug)


#: what the file system answers when the output cannot be written for a reason the user can act on (a full disk or
#: quota, a file too large, a name over 255 bytes or a path over PATH_MAX, a read-only file system): a refusal, exit
#: 2. Every writer writes into a temporary and renames it (``torchcal._outdir``), so nothing half-written stays.
_REFUSED_ERRNOS = frozenset(
    getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EFBIG", "ENAMETOOLONG", "EROFS") if hasattr(errno, n)
)


def _internal_error(command: str, e: BaseException, debug: bool) -> int:
    """Exit 1 with a one-line summary and where to report it (a bug; never a bare traceback)."""
    if debug:
        traceback.print_exc()
    first = _console.one_line(str(e).strip().splitlines()[0]) if str(e).strip() else ""
    print(f"torchcal {command}: internal error: {type(e).__name__}: {first[:300]}", file=sys.stderr)
    print(
        f"torchcal {command}: this is a bug; please report it at {REPORT_TO} with the command line"
        + ("" if debug else " and the output of the same command with --debug"),
        file=sys.stderr,
    )
    return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
