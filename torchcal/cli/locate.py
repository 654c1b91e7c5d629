"""The ``locate`` command: the instrument's rough pose from a few points at poses of the nominal robot."""

from __future__ import annotations

import argparse
import json
import math

from torchcal import _console
from torchcal.cli._args import _add_common, _add_force, _add_robot, _add_units, _tool
from torchcal.cli._common import _reading, _robot_input, json_out_file


def add_parser(sub: argparse._SubParsersAction) -> None:
    lo = sub.add_parser(
        "locate",
        help="the instrument's rough pose from three or more points at poses of the nominal robot (for plan --tracker)",
        description="Before any calibration: fit where the instrument stands from three or more points measured at "
        "known joints, by the nominal robot and a lever arm (with four or more points whose tool orientations "
        "differ by 10 deg or more, the lever arm is fitted too, about --tool). Prints the instrument's position in "
        "the robot's base frame as X,Y,Z [mm] on stdout, the form plan --tracker takes; stderr says how well the "
        "points agree. It is a start for planning: the calibration fits the pose itself.",
    )
    lo.add_argument("points", help="measurement file with q1..qN and x,y,z of three or more points")
    _add_robot(lo)
    lo.add_argument(
        "--tool",
        type=_tool,
        default=None,
        metavar="X,Y,Z",
        help="the probe on the flange [mm] (default 0,0,100): held with three points, the prior's centre with more",
    )
    lo.add_argument(
        "--fit-tool",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="fit the lever arm too (default: where four or more points turn the tool by 10 deg or more)",
    )
    lo.add_argument("--out", default=None, help="also write the pose, lever arm and residual as JSON to this file")
    _add_force(lo)
    _add_units(lo)
    _add_common(lo)


def handle(args) -> int:
    import torch

    from torchcal.data import read_measurements
    from torchcal.data.header import check_header_robot
    from torchcal.robot import load_robot
    from torchcal.use.locate import locate

    inputs = [args.points, *_robot_input(args.robot)]
    out_file = None if args.out is None else json_out_file(args.out, inputs, args.force, "torchcal locate")
    robot = load_robot(args.robot, base_link=args.base_link, tip_link=args.tip_link)
    data = read_measurements(
        args.points,
        require_positions=True,
        min_poses=3,
        purpose="locating the instrument",
        **_reading(args, robot),
    )
    check_header_robot(data, args.robot, robot, f"--robot {args.robot}")
    lever = None if args.tool is None else torch.tensor(args.tool, dtype=torch.float64, device="cpu")
    found = locate(robot, data.q, data.p, lever=lever, fit_lever=args.fit_tool)
    xyz = [float(v) * 1e3 for v in found.tracker_in_base()]
    arm = ", ".join(f"{float(v) * 1e3:.1f}" for v in found.lever)
    _console.info(
        f"located the instrument from {found.n} points: {found.rms * 1e3:.3g} mm RMS between the measured points and "
        f"the nominal robot's; lever arm ({arm}) mm "
        + ("fitted" if found.lever_fitted else "as given (three points, or a tool that hardly turned, do not fix it)")
        + f"; the instrument {math.dist(xyz, (0, 0, 0)) / 1e3:.2f} m from the base"
    )
    if out_file is not None:
        text = json.dumps({"written_by": "torchcal locate", **found.to_dict()}, indent=1, allow_nan=False) + "\n"
        out_file.parent.mkdir(parents=True, exist_ok=True)
        out_file.write_text(text, encoding="utf-8")
    print(",".join(f"{v:.0f}" for v in xyz))
    return 0
