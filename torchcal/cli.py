"""The ``torchcal`` command (CONTRACT §3). Messages go to stderr, results to files under ``--out``."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch

from torchcal import _console
from torchcal.errors import TorchcalError

F64 = torch.float64


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bars or messages on stderr")


def _add_robot(p: argparse.ArgumentParser, required: bool = True) -> None:
    p.add_argument("--robot", required=required, default=None if required else "ur5",
                   help="built-in name (ur5, ur10, panda, ...), a URDF file or a DH YAML file")
    p.add_argument("--base-link", default=None, help="URDF: first link of the chain (default: the root)")
    p.add_argument("--tip-link", default=None, help="URDF: last link of the chain (default: the only deepest leaf)")


def _add_units(p: argparse.ArgumentParser) -> None:
    p.add_argument("--length-unit", choices=["m", "mm"], default="m", help="unit of x,y,z,sx,sy,sz in the file")
    p.add_argument("--angle-unit", choices=["rad", "deg"], default="rad", help="unit of the joint columns")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchcal", description="Robot arm calibration from laser-tracker data.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("simulate", help="simulate a laser-tracker campaign (train.csv, test.csv, truth.json)",
                       description="Simulate a laser-tracker campaign: biased geometry, unknown tracker pose and lever "
                       "arm, tracker and joint noise, and the non-geometric effects asked for.")
    _add_robot(s)
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument("--poses", type=int, default=800, help="static poses in train.csv (default 800)")
    s.add_argument("--test-poses", type=int, default=200, help="static poses in test.csv (default 200)")
    s.add_argument("--trajectory", action="store_true",
                   help="a continuous trajectory instead of static poses (train = first --train-samples)")
    s.add_argument("--path", default="p2p", choices=("p2p", "multisine", "randomwalk", "sweeps"),
                   help="trajectory family: p2p (point-to-point program, default), multisine (smooth, never "
                   "repeating, most of the joint range), randomwalk (slow), sweeps (one cycle repeated)")
    s.add_argument("--samples", type=int, default=7342, help="trajectory samples (default 7342, as the paper)")
    s.add_argument("--train-samples", type=int, default=5874, help="trajectory samples for training (default 5874)")
    s.add_argument("--seed", type=int, default=0, help="random seed; the campaign is reproducible from it")
    s.add_argument("--effect", action="append", default=[], metavar="KIND[:JOINT][=SIZE]",
                   help="inject an effect; repeatable. KIND: compliance, backlash, cyclic (need :JOINT), "
                   "drift (:t or :temperature), field (smooth 6-29-3 network field). SIZE is the RMS probe "
                   "displacement with a unit, e.g. compliance:2=50um, field=0.6mm")
    s.add_argument("--tracker-noise", type=float, default=15.0, help="tracker noise per axis [um] (default 15)")
    s.add_argument("--joint-noise", type=float, default=0.0005, help="joint reading noise [deg] (default 0.0005)")
    s.add_argument("--length-bias", type=float, default=0.1, help="sigma of the geometric length biases [mm]")
    s.add_argument("--angle-bias", type=float, default=0.01, help="sigma of the geometric angle biases [deg]")
    s.add_argument("--no-sigma", action="store_true", help="leave out the sx,sy,sz columns")
    s.add_argument("--length-unit", choices=["m", "mm"], default="m", help="unit of x,y,z,sx,sy,sz in the files")
    _add_common(s)

    c = sub.add_parser("calibrate", help="fit the robot to measurements and write a run directory",
                       description="Fit the robot to laser-tracker measurements (CONTRACT §1 file) and write the run "
                       "directory: report.json, report.md with plots, robot_calibrated.urdf, model for predict.")
    c.add_argument("data", help="measurement file (CSV, CONTRACT §1)")
    _add_robot(c)
    c.add_argument("--out", required=True, help="run directory to write")
    c.add_argument("--method", default=None,
                   help="auto (default: geometry, then a learned residual model where validation data demand it), "
                   "kinematic, pcm (paper Eq. 10 + network), kinematic+ann (kinCalib+), "
                   "integrated (the paper's ANN-EKF; needs a continuous trajectory with a monotonic t column)")
    c.add_argument("--engine", choices=("auto", "adaptive", "ekf"), default="auto",
                   help="integrated method: auto (default: the engines and their settings, and geometry alone, "
                   "judged on the last 20 %% of the training samples; the best is kept only if it beats geometry), "
                   "adaptive (geometry and network in one filter state) or ekf (the paper's filter on the kinematic "
                   "calibration's geometry)")
    c.add_argument("--seed", type=int, default=0, help="seed of the held-out split and the network")
    c.add_argument("--holdout", type=float, default=0.2, help="held-out fraction (default 0.2)")
    c.add_argument("--tracker-noise", type=float, default=15.0,
                   help="tracker noise per axis [um] when the file has no sx,sy,sz (default 15)")
    c.add_argument("--joint-noise", type=float, default=0.0005, help="joint reading noise [deg] (default 0.0005)")
    c.add_argument("--rank-tol", type=float, default=None, help="identifiability tolerance (default 1e-6)")
    _add_units(c)
    _add_common(c)

    pr = sub.add_parser("predict", help="predict probe positions with a calibrated run",
                        description="Predict the probe position in the tracker frame for every row of DATA with "
                        "everything the run learned (geometry, effects, network).")
    pr.add_argument("run", help="run directory written by calibrate")
    pr.add_argument("data", help="file with q1..qN (and t, temperature when the run uses them)")
    pr.add_argument("--out", required=True, help="CSV to write: x,y,z [m] plus the q* and t columns")
    _add_units(pr)
    _add_common(pr)

    cv = sub.add_parser("convert", help="convert a third-party data set into a measurement file",
                        description="Convert a third-party data set into a CONTRACT §1 measurement file.")
    cv.add_argument("source", help="the file to convert")
    cv.add_argument("--from", dest="fmt", required=True, choices=["ipa-robot-accuracy"],
                    help="ipa-robot-accuracy: Series_*/measurements_*.csv of the UR10 + Leica data set "
                    "(Landgraf et al., IEEE CASE 2021, MIT licence)")
    cv.add_argument("--out", required=True, help="measurement file to write")
    _add_common(cv)

    d = sub.add_parser("demo", help="run the main job end to end on built-in simulated data",
                       description="Simulate a UR5 campaign with effects the nominal model lacks (joint-2 compliance "
                       "and a smooth field), close the loop and print the error before and after every step.")
    d.add_argument("--out", default="runs/demo", help="output directory (default runs/demo)")
    d.add_argument("--seed", type=int, default=0)
    _add_common(d)
    return parser


def cmd_calibrate(args) -> int:
    from torchcal import calibrate as C
    from torchcal.data import read_measurements
    from torchcal.report import write_run
    from torchcal.robot import load_robot

    robot = load_robot(args.robot, base_link=args.base_link, tip_link=args.tip_link)
    opts = C.Options(method=args.method or C.DEFAULT_METHOD, seed=args.seed, holdout=args.holdout,
                     sigma_tracker=args.tracker_noise * 1e-6, sigma_joint=math.radians(args.joint_noise),
                     engine=args.engine)
    if args.rank_tol is not None:
        opts.rank_tol = args.rank_tol
    data = read_measurements(args.data, dof=robot.dof, joint_limits=robot.limits, length_unit=args.length_unit,
                             angle_unit=args.angle_unit, require_positions=True,
                             min_poses=C.min_poses(robot, opts.holdout), robot_name=robot.name,
                             purpose=f"a {opts.method} calibration of '{robot.name}'")
    run = C.calibrate(args.robot, data, opts, base_link=args.base_link, tip_link=args.tip_link)
    out = write_run(run, args.out)
    st = {s.name: s for s in run.stages}
    _console.info(f"held-out RMSE: nominal {st['nominal'].rmse * 1e3:.4f} mm, geometric "
                  f"{st['geometric'].rmse * 1e3:.4f} mm, final {run.stages[-1].rmse * 1e3:.4f} mm")
    _console.info(f"wrote {out / 'report.json'} and {out / 'report.md'}")
    return 0


def cmd_predict(args) -> int:
    from dataclasses import replace

    from torchcal.data import read_measurements, write_measurements
    from torchcal.report import load_model, predict

    model, _ = load_model(args.run)
    robot = model.robot
    data = read_measurements(args.data, dof=robot.dof, joint_limits=robot.limits, length_unit=args.length_unit,
                             angle_unit=args.angle_unit, require_positions=False, robot_name=robot.name)
    p = predict(args.run, data)
    out = replace(data, p=p, sigma=None, temperature=None, extra={}, meta={"predicted_by": str(args.run)})
    write_measurements(args.out, out)
    _console.info(f"wrote {len(p)} predictions to {args.out}")
    return 0


def cmd_convert(args) -> int:
    from torchcal.data import convert_ipa

    m = convert_ipa(args.source, args.out)
    _console.info(f"wrote {m.n} poses to {args.out} (series {m.meta.get('series', '?')})")
    return 0


def cmd_simulate(args) -> int:
    from torchcal.sim import EffectSpec, SimConfig, simulate, write_campaign

    cfg = SimConfig(
        robot=args.robot, poses=args.poses, test_poses=args.test_poses, trajectory=args.trajectory,
        path=args.path, samples=args.samples, train_samples=args.train_samples, seed=args.seed,
        sigma_tracker=args.tracker_noise * 1e-6, sigma_joint_deg=args.joint_noise, sigma_length=args.length_bias * 1e-3,
        sigma_angle_deg=args.angle_bias, effects=[EffectSpec.parse(e) for e in args.effect],
        write_sigma=not args.no_sigma, base_link=args.base_link, tip_link=args.tip_link,
    )
    what = "a trajectory" if cfg.trajectory else "static poses"
    _console.info(f"simulating {what} for '{cfg.robot}' (seed {cfg.seed})")
    campaign = simulate(cfg)
    if args.length_unit == "mm":
        campaign = _to_mm(campaign)
    paths = write_campaign(campaign, args.out)
    for path in paths.values():
        _console.info(f"wrote {path}")
    return 0


def _to_mm(campaign):
    from dataclasses import replace

    def mm(m):
        return replace(m, p=m.p * 1000.0, sigma=None if m.sigma is None else m.sigma * 1000.0,
                       meta={**m.meta, "length_unit": "mm"})

    campaign.train, campaign.test = mm(campaign.train), mm(campaign.test)
    campaign.truth["files"]["length_unit"] = "mm"
    return campaign


DEMO_EFFECTS = ("compliance:2=60um", "field=0.05mm")


def cmd_demo(args) -> int:
    from torchcal import calibrate as C
    from torchcal.report import predict, write_run
    from torchcal.sim import EffectSpec, SimConfig, simulate, write_campaign

    out = Path(args.out)
    cfg = SimConfig(robot="ur5", poses=800, test_poses=200, seed=args.seed,
                    effects=[EffectSpec.parse(e) for e in DEMO_EFFECTS])
    _console.info("torchcal demo: a simulated UR5 laser-tracker campaign (800 + 200 poses) with biased geometry, "
                  "joint-2 compliance (60 um RMS at the probe) and a smooth non-geometric field (0.05 mm RMS), "
                  "neither of which the nominal model declares")
    campaign = simulate(cfg)
    paths = write_campaign(campaign, out / "data")
    run = C.calibrate(cfg.robot, campaign.train, C.Options(seed=args.seed))
    run_dir = write_run(run, out / "run")
    p = predict(run_dir, campaign.test)
    test_rmse = float((p - campaign.test.p).norm(dim=-1).square().mean().sqrt())
    summary = {"data": {k: str(v) for k, v in paths.items()}, "run": str(run_dir), "simulated": list(DEMO_EFFECTS),
               "holdout_rmse_mm": {s.name: s.rmse * 1e3 for s in run.stages}, "test_file_rmse_mm": test_rmse * 1e3,
               "stages": [s.name for s in run.stages],
               "effects": [{"kind": e["kind"], "joint": e["joint"]} for e in run.effects_report]}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
    print(f"simulated, undeclared: {', '.join(DEMO_EFFECTS)}")
    print("model                                          held-out RMSE [mm]   max [mm]")
    labels = {"nominal": "nominal geometry (tracker, lever fitted)", "geometric": "after the kinematic calibration",
              "learned": "+ learned residual model"}
    found = {e.get("label"): e for e in run.effects_report}
    for s in run.stages:
        label = labels.get(s.name, f"+ {s.name}")
        if s.name in found and "log10_p" in found[s.name]["evidence"]:
            label += f" (p = 1e{found[s.name]['evidence']['log10_p']:.0f})"
        print(f"{label:47s} {s.rmse * 1e3:12.4f}   {float(s.holdout_errors.max()) * 1e3:9.4f}")
    print(f"{'final model on the separate test file':47s} {test_rmse * 1e3:12.4f}")
    named = [f"{e['kind']}" + (f" (joint {e['joint']})" if e["joint"] is not None else "") for e in run.effects_report]
    print(f"effects found: {', '.join(named) if named else 'none'}")
    print(f"report: {run_dir / 'report.md'}")
    return 0


COMMANDS = {"simulate": cmd_simulate, "calibrate": cmd_calibrate, "predict": cmd_predict, "convert": cmd_convert,
            "demo": cmd_demo}


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _console.set_quiet(getattr(args, "quiet", False))
    try:
        return COMMANDS[args.command](args)
    except TorchcalError as e:
        print(f"torchcal {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
