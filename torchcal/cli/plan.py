"""The ``plan`` command: the poses to measure for a calibration."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from torchcal import _console
from torchcal._outdir import check_out_file
from torchcal.cli._args import (
    JOINT_DEG,
    METHOD_CHOICES,
    TRACKER_UM,
    _add_common,
    _add_force,
    _add_units,
    _count,
    _number,
    _seed,
    _tool,
)
from torchcal.cli._common import _one_torch_thread, _reading, _robot_input, json_out_file
from torchcal.errors import OptionError


def add_parser(sub) -> None:
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
        "stochastic model and variance factor; candidates are sampled within its calibrated region, the joints it "
        "barely moved (narrow) over their limits",
    )
    pl.add_argument(
        "--station",
        default=None,
        help="a --run calibrated from several stations: plan for this one's placement (default the first)",
    )
    pl.add_argument(
        "--probe", default=None, help="a --run with several probes: plan for this one's lever arm (default the first)"
    )
    pl.add_argument(
        "--candidates",
        default=None,
        help="file with q1..qN per row (other columns ignored, but for its load columns: payload, payload_x..z, "
        "tau1..tauN are kept in the planned rows, each pose with its load)",
    )
    pl.add_argument(
        "--payload-levels",
        default=None,
        type=_levels,
        help="KG,KG,...: plan a campaign over these loads: the planned poses take them in turn, in the order they "
        "were picked (every load an equal share of the rows, over the whole planned region), written as a payload "
        "column; the plan's JSON names the loads and the rows each. Without link masses or measured torques, give "
        "two loads or more: one load cannot tell a joint's stiffness from its links' weight",
    )
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
    _add_design(pl)
    _add_force(pl)
    _add_units(pl)
    _add_common(pl)


def _add_design(pl) -> None:
    """plan's design: the criterion, the method planned for and its shares of picks, the scene and the noise levels."""
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


def _plan_side_file(path: Path, inputs: list, force: bool) -> Path:
    """``plan``'s summary next to its poses, replaced like a marked file where an earlier plan wrote it."""
    if path.suffix == ".json":
        return json_out_file(str(path), inputs, force, "torchcal plan")
    return check_out_file(str(path), inputs=inputs, force=force)


def _levels(text: str) -> tuple[float, ...]:
    from torchcal.use.plan import plan_loads

    try:
        levels = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected payloads in kg, comma-separated (0,5,10), got {text!r}") from None
    try:
        plan_loads(1, levels)
    except OptionError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return levels


def _setting(args):
    """What the plan is made for (``--run`` or ``--robot``), with ``--tracker``, ``--tool`` and the noise options
    where given."""
    from torchcal.use.planning import robot_setting, run_setting

    if args.run is not None:
        setting = run_setting(args.run, args.robot, args.method, args.station, args.probe)
    else:
        setting = robot_setting(args.robot, args.base_link, args.tip_link, args.method)
    setting = setting.with_scene(args.tracker, args.tool)
    if args.tracker_noise is not None:
        setting.sigma_tracker = args.tracker_noise * 1e-6
    if args.joint_noise is not None:
        setting.sigma_joint = math.radians(args.joint_noise)
    return setting


def _candidates(args, setting):
    """The candidate poses, their load columns and the words that say where they came from: the ``--candidates``
    file's distinct poses, else ``--pool`` sampled ones."""
    from torchcal.data import read_measurements
    from torchcal.data.header import check_header_robot
    from torchcal.use.plan import sample_candidates
    from torchcal.use.planning import file_candidates, sampling_region

    robot, name = setting.model.robot, setting.robot_name
    if args.candidates is not None:
        data = read_measurements(args.candidates, require_positions=False, **_reading(args, robot))
        check_header_robot(data, name, robot, f"--robot {name}")
        q, loads, repeated = file_candidates(data)
        if repeated:
            _console.info(f"plan: {repeated} candidate rows repeat another row's joints: each pose counted once")
        return q, loads, args.candidates
    region, within = sampling_region(setting, args.run is not None)
    _console.info(f"sampling {args.pool} candidate poses the tracker sees{within} (seed {args.seed})")
    q = sample_candidates(
        setting.model, args.pool, args.seed, setting.tracker, setting.lever, need=args.n, region=region
    )
    return q, {}, f"{len(q)} sampled{within} (seed {args.seed})"


@_one_torch_thread
def handle(args) -> int:
    from torchcal.data import read_measurements
    from torchcal.data.header import check_header_robot
    from torchcal.use.plan import PlanOptions, plan_poses
    from torchcal.use.planning import side_paths, write_plan

    inputs = [p for p in (args.candidates, args.work, args.run) if p] + (_robot_input(args.robot) if args.robot else [])
    out_file = check_out_file(args.out, inputs=inputs, force=args.force)
    side = {k: _plan_side_file(p, inputs, args.force) for k, p in side_paths(out_file).items()}
    if args.run is None and args.robot is None:
        raise OptionError("give --robot or --run (the robot to plan for)")
    setting = _setting(args)
    work = None
    if args.work is not None:
        robot, name = setting.model.robot, setting.robot_name
        wd = read_measurements(args.work, require_positions=False, **_reading(args, robot))
        check_header_robot(wd, name, robot, f"--robot {name}")
        work = wd.q
    q, loads, source = _candidates(args, setting)
    if args.n > len(q):
        raise OptionError(f"--n {args.n} is more than the {len(q)} candidates")
    opts = PlanOptions.for_method(
        setting.method,
        args.n,
        criterion=args.criterion,
        edge_share=args.edge_share,
        learned_share=args.learned_share,
        spread_share=args.spread_share,
        sigma_tracker=setting.sigma_tracker,
        sigma_joint=setting.sigma_joint,
        s0_sq=setting.s0_sq,
        seed=args.seed,
    )
    plan = plan_poses(setting.model, q, opts, work)
    write_plan(
        out_file,
        plan,
        robot_name=setting.robot_name,
        source=source,
        loads=loads,
        payload_levels=args.payload_levels,
        poses_label=args.out,
    )
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
