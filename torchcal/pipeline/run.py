"""Calibration runs: the data split, the screening, then the method's stages (:mod:`torchcal.pipeline.methods`).

Held-out split: a seeded random 20 % of the poses (static data) or the last 20 % of the samples (trajectories, see
:func:`is_trajectory`), never used for fitting. Poses that revisit a joint configuration (all joints within
``Options.group_tol``) go wholly to one side (:func:`torchcal.stats.split`). Gross errors are screened out of both
sides before any stage sees them.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os

import torch

from torchcal import _console
from torchcal import stats as S
from torchcal._method import Method
from torchcal._threads import torch_threads
from torchcal.data import Measurements
from torchcal.effects import MeasurementModel
from torchcal.errors import MeasurementFileError, OptionError
from torchcal.pipeline.checks import (
    MAX_PRIOR_RATIO,
    MIN_HOLDOUT,
    check_corrections,
    check_holdout,
    check_poses,
    check_repeated_rows,
    narrow_joints,
    narrow_note,
)
from torchcal.pipeline.integrated import require_trajectory
from torchcal.pipeline.methods import METHOD_TABLE, PRIOR_METHOD
from torchcal.pipeline.options import DEFAULT_METHOD, METHODS, Options
from torchcal.pipeline.prior import MIN_PRIOR_POSES, Prior, for_data, prior_from_run
from torchcal.pipeline.state import CalibrationRun, Checkpoint
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor

__all__ = [
    "DEFAULT_METHOD",
    "MAX_PRIOR_RATIO",
    "METHODS",
    "MIN_HOLDOUT",
    "MIN_PRIOR_POSES",
    "Prior",
    "CalibrationRun",
    "Options",
    "Checkpoint",
    "calibrate",
    "check_corrections",
    "check_holdout",
    "check_poses",
    "holdout_split",
    "is_trajectory",
    "min_poses",
    "prior_from_run",
    "drop_gross_orientations",
    "screen_gross_errors",
]


def is_trajectory(m: Measurements, max_step: float = 0.05) -> bool:
    """A continuous trajectory: a non-decreasing ``t`` and consecutive samples close in joint space.

    Static poses are taken one after another too (their ``t`` also grows), but the robot moves
    far between them; along a sampled trajectory the median largest joint step between two
    samples is small (below ``max_step`` rad).
    """
    if m.t is None or m.n < 3 or not bool((torch.diff(m.t) >= 0).all()):
        return False
    steps = torch.diff(m.q, dim=0).abs().max(dim=-1).values
    if m.probe is not None:  # several probes measured at one set of joints: the steps between poses
        steps = steps[steps > 0]
        if len(steps) == 0:
            return False
    return float(steps.median()) < max_step


def holdout_split(
    m: Measurements, holdout: float, seed: int, trajectory: bool, group_tol: float = S.GROUP_TOL
) -> S.Split:
    """Training and held-out indices (module docstring): the run's split, also of its training poses.

    With several stations or probes the split is stratified: each station (each probe's rows in it) is split on its
    own with the same share, so that every station and probe is on both sides; revisits are grouped within each
    stratum. Rows of several probes that share one set of joints (one visit of a nest) are revisits of each other
    and stay together."""
    strata = _strata(m)
    if strata is None or trajectory:
        return S.split(m.n, S.holdout_count(m.n, holdout), seed=seed, last=trajectory, q=m.q, group_tol=group_tol)
    keep, out, merged_groups, merged_rows = [], [], 0, 0
    for k, rows in enumerate(strata):
        part = S.split(
            len(rows),
            S.holdout_count(len(rows), holdout),
            seed=seed + k,
            q=m.q[rows.to(m.q.device)],
            group_tol=group_tol,
        )
        if _poses(m.q[rows[part.keep].to(m.q.device)]) < MIN_STATION_ROWS:  # its placement needs them all: none held
            keep.append(rows)
            continue
        keep.append(rows[part.keep])
        out.append(rows[part.held])
        merged_groups += part.merged_groups
        merged_rows += part.merged_rows
    held = torch.sort(torch.cat(out)).values if out else torch.zeros(0, dtype=torch.long, device=strata[0].device)
    return S.Split(torch.sort(torch.cat(keep)).values, held, merged_groups, merged_rows)


#: poses an instrument placement needs: three points fix its six parameters (the rows of several probes at one pose
#: count once: the closed-form start places a station before the lever arms are known)
MIN_STATION_ROWS = 3


def _poses(q: Tensor) -> int:
    """The number of distinct poses (joint rows) in ``q (N, dof)``."""
    return int(len(torch.unique(q, dim=0))) if len(q) else 0


def check_stations(m: Measurements) -> None:
    """Refuse a station measured at fewer than :data:`MIN_STATION_ROWS` poses, naming the file, the station and its
    lines: its pose cannot be fitted (the rigid fit of its rows is undetermined)."""
    if m.station is None or m.n_stations < 2:
        return
    st = m.station.cpu()
    for k, name in enumerate(m.station_names):
        rows = torch.nonzero(st == k).flatten()
        n = _poses(m.q[rows.to(m.q.device)])
        if 0 < n < MIN_STATION_ROWS:
            where = ", ".join(str(m.lines[i] if m.lines else i) for i in rows.tolist())
            raise MeasurementFileError(
                m.source or "the measurements",
                f"station {name!r} was measured at {n} pose{'s' if n > 1 else ''} ({len(rows)} rows, lines {where}); "
                f"an instrument placement needs at least {MIN_STATION_ROWS} poses to fix its pose (6 parameters): "
                "measure more points from it, or drop its rows",
                line=m.lines[int(rows[0])] if m.lines else int(rows[0]) + 1,
                column="station",
                hint="label the rows of one instrument placement with one station name; a label per row makes every "
                "row its own placement",
            )


def _strata(m: Measurements) -> list[Tensor] | None:
    """Row indices of each station (None for a single station): probes of one nest share their joints and are
    grouped as revisits within it, so the station alone stratifies."""
    if m.station is None or m.n_stations < 2:
        return None
    st = m.station.cpu()
    return [torch.nonzero(st == s).flatten() for s in range(m.n_stations) if bool((st == s).any())]


def min_poses(robot: RobotModel, holdout: float) -> int:
    """Poses needed for a kinematic calibration: 3 observations each, twice the parameters, then the holdout."""
    n_par = int(robot.geometry.mask.sum()) + 9
    return int(math.ceil(2 * n_par / 3 / (1.0 - holdout)))


def _robot(robot: RobotModel | str | os.PathLike, base_link: str | None, tip_link: str | None) -> RobotModel:
    if isinstance(robot, RobotModel):
        return robot
    from torchcal.robot import load_robot

    return load_robot(robot, base_link=base_link, tip_link=tip_link)


def start(
    robot: RobotModel | str | os.PathLike,
    data: Measurements,
    opts: Options,
    *,
    robot_spec: str | os.PathLike | None = None,
    base_link: str | None = None,
    tip_link: str | None = None,
    prior: Prior | None = None,
) -> CalibrationRun:
    """The run before its first stage: the data checked and split, the gross errors screened out, the nominal model
    with its calibrated region (the training poses); from a ``prior``, its model with its region, unscreened."""
    if data.p is None:
        raise OptionError("calibration needs measured positions (x, y, z columns)")
    if prior is not None:
        if opts.method != Method.KINEMATIC:
            raise OptionError(f"a calibration from a prior run is kinematic, not method '{opts.method}'")
        prior = for_data(prior, data)  # its stations and probes matched by label to the rows'
        robot = prior.model.robot
    spec = robot_spec if robot_spec is not None else (robot if not isinstance(robot, RobotModel) else robot.source)
    robot = _robot(robot, base_link, tip_link).to(opts.device)  # the run computes on opts.device
    if prior is None and (data.n_stations > 1 or data.n_probes > 1):  # one pose per station, one lever per probe
        robot = copy.deepcopy(robot)
        robot.set_stations(data.station_names if data.n_stations > 1 else None)
        robot.set_probes(data.probe_names if data.n_probes > 1 else None)
    data = data.to(opts.device)
    if data.dof != robot.dof:
        raise OptionError(f"data have {data.dof} joints but robot '{robot.name}' has {robot.dof}")
    check_poses(data)
    check_repeated_rows(data)
    check_stations(data)
    opts = with_robot_tolerances(opts, robot)
    method = METHOD_TABLE[opts.method]
    trajectory = is_trajectory(data) if opts.split.trajectory is None else bool(opts.split.trajectory)
    if method.trajectory_only:
        require_trajectory(data, trajectory)
    split = holdout_split(data, opts.split.holdout, opts.seed + S.Stream.HOLDOUT, trajectory, opts.split.group_tol)
    if prior is None:
        tr, ho, screening = screen_gross_errors(robot, data, *split, opts, trajectory)
        data = drop_gross_orientations(data, split.keep, split.held, screening)
        model = MeasurementModel(robot)
        model.set_region(data.q[tr], fade=method.fades)
    else:  # the robust screening fits the geometry from scratch, which the few rows of an update cannot
        tr, ho, screening = split.keep, split.held, None
        model = copy.deepcopy(prior.model).to(opts.device)
    from torchcal.pipeline.records import Note

    notes = ()
    if split.merged_groups:
        notes = (
            Note(
                "split",
                f"split: {split.merged_groups} revisited joint configurations ({split.merged_rows} poses) "
                f"kept wholly on one side",
            ),
        )
    # an update's few rows move little; its model's region is the prior run's, which said its own narrow joints
    narrow = None if prior is not None else narrow_note(narrow_joints(data.q[tr], robot.limits, robot.joint_types))
    if narrow is not None:  # said before any fitting: the user learns it even if the run stops
        _console.info(f"warning: {narrow}")
        notes += (Note("region", narrow),)
    return CalibrationRun(
        spec, model, opts, data, tr, ho, trajectory, split=split, screening=screening, notes=notes, prior=prior
    )


def with_robot_tolerances(opts: Options, robot: RobotModel) -> Options:
    """``opts`` with the kinematic calibration's tolerance priors the robot's file declares (``tolerances:`` of a DH
    table, :func:`torchcal.robot.load.load_dh_yaml`): a robot's own manufacturing tolerances replace the defaults
    (0.1 mm, 0.01 deg); options that switch the tolerance priors off (None) keep them off."""
    tol = getattr(robot, "tolerances", None)
    if tol is None or opts.fit.tolerance_length is None or opts.fit.tolerance_angle is None:
        return opts
    fit = dataclasses.replace(opts.fit, tolerance_length=tol[0], tolerance_angle=tol[1])
    return dataclasses.replace(opts, fit=fit)


def calibrate(
    robot: RobotModel | str | os.PathLike,
    data: Measurements,
    opts: Options | None = None,
    *,
    robot_spec: str | os.PathLike | None = None,
    base_link: str | None = None,
    tip_link: str | None = None,
    prior: Prior | None = None,
) -> CalibrationRun:
    """Run a calibration: the method's stages (:mod:`torchcal.pipeline.methods`) in order, each result applied.

    Args:
        robot: the robot, nominal; a built-in name or description file is loaded with ``base_link`` and
            ``tip_link``. The run works on a copy: the robot passed is not changed.
        data: measurements with positions.
        opts: the run's options (default :class:`Options`).
        robot_spec: how the report names the robot's description (default: the spec passed as ``robot``, or the
            robot's source file).
        prior: a prior run (:func:`torchcal.pipeline.prior.prior_from_run`): the calibration starts from its model
            and fits the changes to it (MAP, :data:`~torchcal.pipeline.methods.PRIOR_METHOD`); ``robot`` then only
            names the robot (its name must be the prior's). The method is kinematic (``auto`` means it too).
    """
    opts = opts or Options()
    if prior is not None:
        named = _robot(robot, base_link, tip_link).name
        if named != prior.model.robot.name:
            raise OptionError(f"the prior run calibrated robot '{prior.model.robot.name}', not '{named}'")
        if opts.method == DEFAULT_METHOD:
            opts = dataclasses.replace(opts, method=Method.KINEMATIC)
    run = start(robot, data, opts, robot_spec=robot_spec, base_link=base_link, tip_link=tip_link, prior=prior)
    stages = (PRIOR_METHOD if prior is not None else METHOD_TABLE[opts.method]).stages
    for stage in _console.progress(stages, desc="calibrate: stages"):
        run = run.apply(stage(run))
    return run


def drop_gross_orientations(data: Measurements, tr: Tensor, ho: Tensor, screening) -> Measurements:
    """``data`` with the orientations the screening found gross left out (their rows' positions stay); ``tr`` and
    ``ho`` are the training and held-out indices the screening was given."""
    if screening is None:
        return data
    rows = torch.cat(
        [
            tr[screening.training.orientation_dropped_index.cpu()],
            ho[screening.holdout.orientation_dropped_index.cpu()],
        ]
    )
    if not len(rows):
        return data
    for name, part in (("training", screening.training), ("held-out", screening.holdout)):
        if part.orientation_dropped:
            _console.info(
                f"{len(part.orientation_dropped)} {name} rows' orientations left out as gross errors "
                f"(their positions kept; file lines {_lines(part.orientation_dropped)})"
            )
    return data.drop_orientation(rows.to(data.q.device))


def _lines(rows) -> str:
    return ", ".join(str(r.line) for r in rows[:10]) + (" ..." if len(rows) > 10 else "")


def screen_gross_errors(robot: RobotModel, data: Measurements, tr: Tensor, ho: Tensor, opts: Options, trajectory: bool):
    """The training and held-out rows without their gross errors (:func:`torchcal.estimate.robust.screen_geometric`).

    Returns the kept training and held-out indices into ``data`` and the screening (None when
    ``opts.levels.outlier`` is None). Every later stage sees only the kept rows, and the held-out errors
    leave the rejected held-out rows out; on data without gross errors nothing changes.
    """
    if opts.levels.outlier is None:
        return tr, ho, None
    from torchcal.estimate.robust import screen_geometric

    _console.info("screening for gross errors: robust geometric fit, data snooping")
    with torch_threads(1):  # small kernels (robust reweighting, u x u solves): one thread, as in close_loop
        sc = screen_geometric(
            MeasurementModel(robot),
            data.subset(tr),
            data.subset(ho),
            opts.fit,
            trajectory=trajectory,
            alpha=opts.levels.outlier,
        )
    for name, part in (("training", sc.training), ("held-out", sc.holdout)):
        if part.rejected:
            _console.info(
                f"{len(part.rejected)} {name} rows rejected as gross errors (file lines {_lines(part.rejected)})"
            )
    return tr[sc.training.kept.cpu()], ho[sc.holdout.kept.cpu()], sc
