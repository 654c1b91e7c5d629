"""The ``calibrate`` command: fit the robot to measurements and write a run directory."""

from __future__ import annotations

import argparse
import json
import math

from torchcal import _console
from torchcal._method import ENGINES, Engine
from torchcal._outdir import check_out_dir
from torchcal.cli._args import (
    FRACTION,
    JOINT_DEG,
    METHOD_CHOICES,
    ORIENTATION_DEG,
    POSITIVE,
    RANK_TOL,
    REPLACED_HELP,
    TRACKER_UM,
    _add_computing,
    _add_robot,
    _seed,
    _tool,
)
from torchcal.cli._common import _reading, _robot_input, calibration_module


def add_parser(sub) -> None:
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
    _add_noise_and_tool(c)
    _add_computing(c)


def _add_noise_and_tool(c) -> None:
    """calibrate's noise levels, identifiability tolerance, effect bound and known lever arm."""
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


def handle(args) -> int:
    from torchcal.data.header import check_header_robot

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
    from torchcal.report.markdown import effect_line

    for e in run.effects_report:
        _console.info("effect found: " + effect_line(e))
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
