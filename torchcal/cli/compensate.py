"""The ``compensate`` command: the joint commands that put the probe on targets by a calibrated run."""

from __future__ import annotations

import math
import sys
from typing import TYPE_CHECKING

from torchcal import _console
from torchcal._outdir import check_out_file
from torchcal.cli._args import PAYLOAD_KG, _add_common, _add_force, _add_units, _number
from torchcal.cli._common import _has_load, _one_torch_thread, _reading, warn_outside
from torchcal.errors import TorchcalError

if TYPE_CHECKING:  # the command's module loads without torch (torchcal --help); its handler imports it
    import torch


def add_parser(sub) -> None:
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
        "probe, extra columns, sx,sy,sz, extrapolation, model (full, geometric, physical or nominal: which "
        "model commanded the row), miss, miss_angle [rad] (6-D), status",
    )
    cp.add_argument("--start", default=None, help="CSV with q1..qN: start joints per row (x,y,z-only targets)")
    cp.add_argument(
        "--payload",
        type=PAYLOAD_KG,
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


def _program_load(args, data, model) -> dict:
    """The program's load per row for the context of the compensation: its payload [kg] (``--payload KG``, else the
    targets' ``payload`` column) and the torques its poses hold (the targets' ``tau`` columns), which the run's
    compliance carries. A run whose compliance reads measured torques needs them."""
    from torchcal.use.conditions import require_torques

    require_torques(model, data, str(args.targets))
    payload = _payload_of(args, data)
    return {**({} if payload is None else {"payload": payload}), **({} if data.tau is None else {"tau": data.tau})}


def _payload_of(args, data) -> torch.Tensor | None:
    """``--payload KG`` for every row, else the targets' ``payload`` column, else None (0 kg)."""
    import torch

    if args.payload is not None:
        return torch.full((data.n,), float(args.payload), dtype=torch.float64, device=data.q.device)
    return data.payload


@_one_torch_thread
def handle(args) -> int:
    from torchcal.data import read_measurements
    from torchcal.use.beyond_commands import resolver, targets_of_file
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
    targets_of = targets_of_file(data, six_d)
    res, ext, plain = compensate_groups(
        model, station, probe, targets_of, q_start, at=at_station, context=context, orientation_weight=args.weight
    )
    resolve = resolver(res, station, probe, targets_of, context, args.weight)
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


def _write_compensation(args, out_file, run, data, groups, res, plain_resolve, mode) -> None:
    """Write ``compensate``'s file in the targets file's units: the commands, the program's own joints beside them
    (``q1_program..``), the targets, labels, extra columns, trust columns, the misses and the status. Rows where
    the run gives another model (beyond the region) are solved again with it first
    (:func:`~torchcal.use.beyond_commands.commanded_trust`)."""
    import dataclasses

    from torchcal.effects import Context
    from torchcal.use.beyond_commands import commanded_trust
    from torchcal.use.compensate import file_units, write_joints
    from torchcal.use.rundir import MODEL_NAMES

    (model, meta), (station, probe), (plain, resolve) = run, groups, plain_resolve
    # how far to trust each command: the predicted standard deviation of a measurement there, and which model
    rows = dict(station=station if model.robot.stations else None, probe=probe if model.robot.probes else None)
    load = dict(payload=_payload_of(args, data), tau=data.tau)
    ctx = Context(q=res.q, t=data.t, temperature=data.temperature, **load, **rows)
    sigma, which = commanded_trust(args.run, model, meta, res, ctx, plain, resolve)
    joint, length = file_units(model.robot.joint_types, args.length_unit, args.angle_unit)
    extra = {f"q{k + 1}_program": data.q[:, k] * joint[k] for k in range(data.dof)}
    extra.update(data.extra)
    sigma, ext, conditions = _compensate_load(args, (model, meta), data, res.q, sigma)
    if load["payload"] is not None:  # the payload the commands were solved with (--payload wins over the column)
        extra["payload"] = load["payload"]
    if sigma is not None:
        extra.update(sx=sigma[:, 0] * length, sy=sigma[:, 1] * length, sz=sigma[:, 2] * length)
    extra["extrapolation"] = ext  # of the commands written
    extra["model"] = [MODEL_NAMES[int(i)] for i in which.tolist()]
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

    import torch

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
