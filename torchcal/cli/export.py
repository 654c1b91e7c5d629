"""The ``export`` command: a run's geometry out to other software (UR ROS 2 driver, DH table, URDF)."""

from __future__ import annotations

import argparse
from pathlib import Path

from torchcal import _console
from torchcal._outdir import check_out_file
from torchcal.cli._args import _add_common, _add_force
from torchcal.errors import OptionError


def add_parser(sub: argparse._SubParsersAction) -> None:
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


def handle(args) -> int:
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
