"""The ``simulate`` command: a laser-tracker campaign with known truth (train.csv, test.csv, truth.json)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from torchcal import _console
from torchcal._bounds import MAX_PAYLOAD_KG
from torchcal._outdir import check_out_dir
from torchcal.cli._args import (
    ANGLE_BIAS_DEG,
    JOINT_DEG,
    LENGTH_BIAS_MM,
    ORIENTATION_DEG,
    OUT_HELP,
    PAYLOAD_KG,
    POSITIVE,
    TORQUE_NOISE_NM,
    TRACKER_UM_SIM,
    _add_common,
    _add_robot,
    _count,
    _joint_numbers,
    _seed,
)
from torchcal.cli._common import _robot_input, _simulate
from torchcal.errors import OptionError


def add_parser(sub) -> None:
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
        "displacement with a unit, e.g. compliance:2=50um, coupling:3<-2=50um, field=0.6mm; a coupling may "
        "instead be given by its ratio, coupling:5<-4=1e-3 (dq5 = 1e-3 q4). The tracker's own errors: "
        "tracker_az:H=40urad, tracker_el:H=40urad (encoder harmonic of order H), range_offset=20um, "
        "range_scale=5ppm, axis_tilt=40urad (trunnion axis), beam_tilt=40urad, beam_offset=20um",
    )
    s.add_argument(
        "--tracker-noise", type=TRACKER_UM_SIM, default=15.0, help="tracker noise per axis [um], <= 10000 (default 15)"
    )
    s.add_argument(
        "--joint-noise", type=JOINT_DEG, default=0.0005, help="joint reading noise [deg], <= 1 (default 0.0005)"
    )
    s.add_argument("--length-bias", type=LENGTH_BIAS_MM, default=0.1, help="sigma of the geometric length biases [mm]")
    s.add_argument("--angle-bias", type=ANGLE_BIAS_DEG, default=0.01, help="sigma of the geometric angle biases [deg]")
    _add_layout(s)
    _add_common(s)


def _add_layout(s) -> None:
    """simulate's instrument and campaign layout: a 6-D probe, columns and units, a fixed tool axis, stations and
    probes, loads, a narrow campaign."""
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
    if max(levels) > MAX_PAYLOAD_KG:  # grams: the payload column refuses it too
        raise argparse.ArgumentTypeError(f"payloads are at most {MAX_PAYLOAD_KG:g} kg, got {text!r}")
    return levels


def _add_load_options(s) -> None:
    """simulate's loads: the payload of the training and test rows, levels, measured torques."""
    s.add_argument(
        "--payload", type=PAYLOAD_KG, default=None, metavar="KG", help="payload at the probe of the training rows"
    )
    s.add_argument(
        "--test-payload",
        type=PAYLOAD_KG,
        default=None,
        metavar="KG",
        help="payload of the test rows (default --payload)",
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
        "--torque-noise",
        type=TORQUE_NOISE_NM,
        default=None,
        metavar="NM",
        help="standard deviation of --torques (default 0.5)",
    )


def _check_load_options(args) -> None:
    """Refuse load options that would be dropped without a word (--payload beside --payload-levels, --torque-noise
    without --torques) or that the simulator cannot combine (loads and several stations or probes)."""
    if args.payload is not None and args.payload_levels is not None:
        raise OptionError(
            "--payload and --payload-levels both give the training rows' payload: give one (--payload-levels "
            "cycles the rows over its levels; --test-payload sets the test rows')"
        )
    if args.torque_noise is not None and not args.torques:
        raise OptionError("--torque-noise is the noise of --torques: add --torques, or leave --torque-noise out")
    loads = [
        o
        for o, given in (
            ("--payload", args.payload),
            ("--test-payload", args.test_payload),
            ("--payload-levels", args.payload_levels),
            ("--torques", args.torques or None),
        )
        if given is not None
    ]
    several = [f"{o} {v}" for o, v in (("--stations", args.stations), ("--probes", args.probes)) if v > 1]
    if loads and several:
        raise OptionError(
            f"{', '.join(loads)} with {' and '.join(several)}: simulated loads take one station and one probe; "
            "simulate the loads and the placements as separate campaigns"
        )


def handle(args) -> int:
    from torchcal._outdir import replace_dir
    from torchcal.sim import EffectSpec, SimConfig, write_campaign

    inputs = _robot_input(args.robot)
    out = check_out_dir(args.out, inputs=inputs)
    if args.trajectory and args.train_samples >= args.samples:
        raise OptionError(
            f"--train-samples {args.train_samples} must be below --samples {args.samples} (the rest is the test phase)"
        )
    _check_load_options(args)
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
        payload=0.0 if args.payload is None else args.payload,
        test_payload=args.test_payload,
        payload_levels=args.payload_levels,
        torques=args.torques,
        sigma_torque=0.5 if args.torque_noise is None else args.torque_noise,
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

    import torch

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
