"""The ``predict`` command: probe positions of a calibrated run, with how far to trust each."""

from __future__ import annotations

from torchcal import _console
from torchcal._outdir import check_out_file
from torchcal.cli._args import _add_computing, _add_force
from torchcal.cli._common import _has_load, _one_torch_thread, warn_outside
from torchcal.errors import OptionError


def add_parser(sub) -> None:
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
        "deviation of a new measurement minus the prediction) and model (full: the run's model; beyond the region "
        "the model the run chose there: full, geometric, physical or nominal), plus the q*, t, station and probe "
        "columns (never one of the input files)",
    )
    _add_force(pr)
    _add_computing(pr)


def _prediction_rows(args, model, meta):
    """``predict``'s rows: DATA read for the run's robot (text columns beside the numbers ignored), its header's robot
    and its stations checked against the run's."""
    from torchcal.data import read_measurements
    from torchcal.data.header import check_header_robot
    from torchcal.use.conditions import require_torques
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
    require_torques(model, data, str(args.data))
    return data


def _prediction_trust(args, model, meta, data):
    """How far to trust each row (on the CPU, before the model moves to --device): the standard deviation of a new
    measurement minus the prediction, how far the pose lies outside the calibrated region, and which model predicts
    it (beyond the region, the one with the smaller sigma); a load the run was not fitted at is flagged, its sigma and
    extrapolation grown (:mod:`torchcal.use.conditions`). Returns ``(trust, sigma, extrapolation, load conditions)``."""
    import torch

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
def handle(args) -> int:
    from dataclasses import replace

    import torch

    from torchcal._device import resolve_device
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
