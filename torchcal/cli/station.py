"""The ``station`` command: re-station a calibrated run from a few points at a new instrument placement."""

from __future__ import annotations

import sys
from pathlib import Path

from torchcal import _console
from torchcal._outdir import check_out_dir
from torchcal.cli._args import REPLACED_HELP, _add_common, _add_units
from torchcal.cli._common import _reading


def add_parser(sub) -> None:
    st = sub.add_parser(
        "station",
        help="re-station a calibrated run from a few points measured at a new instrument placement",
        description="Fit the instrument pose (and with --tool the lever arm) of a calibrated run to three or more "
        "points measured from a new placement of the instrument, the robot's calibration unchanged, and write a "
        "run directory that predict and compensate use at the new placement. Its report.json holds a station "
        "block: the new pose, its standard deviations and covariance, the points' residuals and leave-one-out "
        "errors, a chi-square test against the run's predicted error, and the placement's predicted effect on "
        "accuracy over poses like the points (their joint ranges, within the calibrated region). The points' station "
        "column may name the new placement (one name, new or one of the run's): the re-stationed run keeps that name. "
        "The points' load columns (payload, tau1..tauN) are read as calibrate reads them: the run's compliance carries "
        "the load, never the placement or the lever arm; a load beyond the run's training widens the predicted error "
        "by what the points bear out.",
    )
    st.add_argument("run", help="run directory written by calibrate (or by an earlier station)")
    st.add_argument("points", help="measurement file with q1..qN and x,y,z (optional sx,sy,sz) of three or more points")
    st.add_argument("--out", required=True, help="run directory to write; " + REPLACED_HELP)
    st.add_argument(
        "--tool",
        action="store_true",
        help="fit the lever arm too (another tool or probe than the run's; without it, a changed tool is tested and "
        "fitted where the points fit worse than the run predicts and a new lever arm explains most of that; needs "
        "four or more points whose tool orientations differ; refused on a run of several probes, whose lever arms "
        "are kept)",
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


def handle(args) -> int:
    from torchcal.data import read_measurements
    from torchcal.data.header import check_header_robot
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
