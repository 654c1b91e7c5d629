"""Calibration runs: data split, baseline, geometric fit, correction network, held-out errors.

Methods (``--method``):

* ``kinematic``: kinematic calibration (Horvath & Neuner 2024, Eq. 11): the identifiable DH /
  joint-origin errors, the instrument pose and the lever arm, by weighted LM.
* ``pcm``: the paper's position correction model (Eq. 10 + Sec. 2.2): instrument pose and lever
  arm with the nominal geometry, then a :class:`CorrectionNet` on the position corrections.
* ``kinematic+ann``: the literature's sequential "kinCalib+": ``kinematic``, then the network
  on what remains.
* ``auto`` (default): ``kinematic``, then the closed loop (:mod:`torchcal.diagnose`): the named
  effects (compliance, backlash, cyclic, drift) the residuals demand, each chosen by a score test,
  refitted jointly with the geometry and confirmed on validation poses; then a ``learned``
  residual model only where the data demand it: a kernel regression (:mod:`torchcal.effects.kernel`)
  and the correction network are fitted on 80 % of the training poses and judged on the other
  20 %; the better one is kept when it lowers the validation RMSE by at least 5 % and a one-sided
  paired test gives p < 0.01.
* ``integrated``: ``kinematic`` (the reference stage), then the integrated ANN-EKF on a continuous
  trajectory (:mod:`torchcal.pipeline.integrated`): by default (``engine="auto"``) the engines and their settings
  and geometry alone judged on the last block of the training samples, the best kept only where it beats
  geometry; or the adaptive filter with the geometry in its state (``engine="adaptive"``), or the paper's filter
  on the kinematic geometry (``engine="ekf"``).

Held-out split: a seeded random 20 % of the poses (static data) or the last 20 % of the
samples (trajectories, see :func:`is_trajectory`), never used for fitting. Poses that revisit a joint
configuration (all joints within ``Options.group_tol``) go wholly to one side (:func:`torchcal.stats.split`).

The run is the only place that imports the closed loop (:mod:`torchcal.pipeline.loop`), the learned stage
(:mod:`torchcal.pipeline.learned`) and the filters (:mod:`torchcal.pipeline.integrated`); every step appends
its stages and records to the :class:`CalibrationRun`.
"""

from __future__ import annotations

import copy
import math
import os
from dataclasses import dataclass, field

import torch

from torchcal import _console
from torchcal import stats as S
from torchcal._bounds import MAX_RANK_TOL, MAX_SIGMA_JOINT, MAX_SIGMA_TRACKER, MAX_TOOL, check_range
from torchcal._device import resolve_device
from torchcal._threads import torch_threads
from torchcal.data import Measurements
from torchcal.effects import MAX_JOINT_ERROR, MeasurementModel
from torchcal.errors import EstimationError, MeasurementFileError, OptionError
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.estimate.fit import (
    GEOMETRIC_GROUPS,
    Fit,
    errors,
    place_instrument_and_tool,
    prior_ratios,
    solve,
)
from torchcal.estimate.identifiability import DEFAULT_TOL
from torchcal.pipeline.integrated import (
    integrate,
    integrate_adaptive,
    integrate_selected,
    refit_geometry,
    require_trajectory,
)
from torchcal.pipeline.learned import correction_net_stage, learned_stage
from torchcal.pipeline.loop import close_loop, guard_holdout
from torchcal.pipeline.records import EffectRecord, Rejection, StageName
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor
F64 = torch.float64

METHODS = ("auto", "kinematic", "pcm", "kinematic+ann", "integrated")
#: engines of the integrated method (:mod:`torchcal.pipeline.integrated`)
ENGINES = ("auto", "adaptive", "ekf")
DEFAULT_METHOD = "auto"


@dataclass
class Options:
    method: str = DEFAULT_METHOD
    seed: int = 0
    holdout: float = 0.2
    sigma_tracker: float = 15e-6  # m per axis, when the data carry no sx, sy, sz
    sigma_joint: float = math.radians(0.0005)  # rad, joint reading noise
    rank_tol: float = DEFAULT_TOL
    max_iter: int = 100
    hidden: int = 29
    prior_length: float | None = 1e-3  # m: a-priori sigma of the geometric length corrections (None: no prior)
    prior_angle: float | None = math.radians(0.1)  # rad: likewise for angles
    # the lever arm and the instrument pose (README, "Priors"): MAP where the data are weak, held where they add little
    prior_tool: float | None = 0.5  # m: a-priori sigma of the lever arm about the flange centre (None: no prior)
    prior_instrument: tuple[float, float] | None = (0.5, 0.1)  # m, rad: of the instrument pose about the start
    tool: tuple[float, float, float] | None = None  # m: a known lever arm (flange frame), the prior's centre
    tool_sigma: float = 1e-3  # m: the known lever arm's a-priori sigma
    stat_tol: float = 1e-2  # stop LM when a step gains less than 1 % of the variance factor
    net_method: str = "lm"
    net_iterations: int = 100
    trajectory: bool | None = None  # None: decide from a monotonic t column
    diagnose: bool = True  # auto: search the named effects (the closed loop) before the learned stage
    learned: bool = True  # auto: the learned residual model after the closed loop (False: the loop alone)
    learned_hyper: bool = True  # auto: refit a kept GP's hyperparameters in every alternating and pruning refit
    # (False: hold them and only re-condition the GP, pipeline.learned._conditioner: faster, decisions may differ)
    alpha: float = 0.01  # closed loop: family-wise level of the score tests (Bonferroni)
    alpha_validation: float = 0.05  # closed loop: level of the paired validation test
    engine: str = "auto"  # integrated: "auto" (chosen on validation, geometry alone among the candidates),
    # "adaptive" (geometry in the filter state) or "ekf" (the paper's filter)
    outlier_alpha: float | None = 1e-3  # gross-error screening's family-wise level (None: no screening)
    group_tol: float = S.GROUP_TOL  # rad: rows whose joints all agree within it stay on one side of every split
    device: str = "cpu"  # where the run computes: cpu, cuda, cuda:N (torchcal._device.resolve_device)
    max_joint_error: float | None = MAX_JOINT_ERROR  # rad: the largest size a named joint-angle effect may have
    # anywhere on its joint's range (torchcal.effects.joint.MAX_JOINT_ERROR; None: no bound)
    refit: bool | None = None  # the model written fitted again on all samples, training and held-out, once chosen
    # (the held-out errors reported stay those of the fit on the training samples): None means on for the
    # integrated method's auto engine and off otherwise; True is allowed for kinematic too (see ``refits``)

    def __post_init__(self):
        if self.method not in METHODS:
            raise OptionError(f"method '{self.method}' is not one of {', '.join(METHODS)}")
        if self.engine not in ENGINES:
            raise OptionError(f"engine '{self.engine}' is not one of {', '.join(ENGINES)}")
        if self.max_joint_error is not None and not 0.0 < self.max_joint_error <= 0.5:
            raise OptionError(f"max_joint_error must lie in (0, 0.5] rad, got {self.max_joint_error}")
        if not 0.0 < self.holdout < 0.9:
            raise OptionError(f"holdout must lie in (0, 0.9), got {self.holdout}")
        check_range("sigma_tracker", self.sigma_tracker, 0.0, MAX_SIGMA_TRACKER, low_open=True, scale=1e6, unit="um")
        check_range("sigma_joint", self.sigma_joint, 0.0, MAX_SIGMA_JOINT, scale=180 / math.pi, unit="deg")
        check_range("rank_tol", self.rank_tol, 0.0, MAX_RANK_TOL, low_open=True)
        if self.refit and not (self.method == "kinematic" or (self.method == "integrated" and self.engine == "auto")):
            raise OptionError(
                f"refit applies to the kinematic method and the integrated method's auto engine, not to method "
                f"'{self.method}'" + (f" with engine '{self.engine}'" if self.method == "integrated" else "")
            )
        if self.tool is not None and (len(self.tool) != 3 or not self.tool_sigma > 0):
            raise OptionError(
                f"tool must be 3 numbers [m] with a positive tool_sigma, got {self.tool}, {self.tool_sigma}"
            )
        if self.tool is not None:  # a lever arm of metres is a unit mix-up (mm given as m), not a probe
            for k, v in zip("xyz", self.tool):
                check_range(f"tool {k}", v, -MAX_TOOL, MAX_TOOL, scale=1e3, unit="mm")
            check_range("tool_sigma", self.tool_sigma, 0.0, MAX_TOOL, low_open=True, scale=1e3, unit="mm")
        self.device = str(resolve_device(self.device))  # an unknown or absent device raises here, before any work

    @property
    def prior_lever(self) -> float | None:
        """The lever arm's a-priori sigma [m]: ``tool_sigma`` about a known ``tool``, else ``prior_tool``."""
        return self.tool_sigma if self.tool is not None else self.prior_tool

    def lever_prior(self, sigma_noise: float) -> tuple[Tensor, float] | None:
        """The start's lever-arm prior (:func:`~torchcal.estimate.fit.place_instrument_and_tool`): centre ``tool``
        (default the flange centre) [m] and ``sigma_noise^2 / sigma^2`` for a measurement noise ``sigma_noise`` [m]."""
        if self.prior_lever is None:
            return None
        centre = torch.tensor(self.tool if self.tool is not None else (0.0, 0.0, 0.0), dtype=F64, device=self.device)
        return centre, (sigma_noise / self.prior_lever) ** 2

    @property
    def refits(self) -> bool:
        """Whether the model written is fitted again on all samples once chosen (``refit``; None: the integrated
        method's auto engine does, the rest do not). On a trajectory the held-out last samples are the ones
        nearest the path's continuation, and the model a user predicts that continuation with should have them."""
        return self.method == "integrated" and self.engine == "auto" if self.refit is None else bool(self.refit)


@dataclass
class Stage:
    """A model state with its held-out errors, for the before/after story."""

    name: str  # a StageName, or the label of the named effect the stage added
    model: MeasurementModel
    holdout_errors: Tensor  # (N_holdout,) m
    train_errors: Tensor

    @property
    def rmse(self) -> float:
        return S.rmse(self.holdout_errors)


@dataclass
class CalibrationRun:
    """Everything a calibration did, for the report: stages, fits, the effects kept and the candidates rejected."""

    robot_spec: str
    robot: RobotModel
    model: MeasurementModel
    options: Options
    data: Measurements
    train_idx: Tensor
    holdout_idx: Tensor
    trajectory: bool
    stages: list[Stage] = field(default_factory=list)
    fits: list[Fit] = field(default_factory=list)
    covariance: ParameterCovariance | None = None  # of the last fit's free parameters (predict's sx, sy, sz)
    effects: list[EffectRecord] = field(default_factory=list)
    rejections: list[Rejection] = field(default_factory=list)  # candidates that did not earn their place
    notes: list[str] = field(default_factory=list)
    learned_validation_errors: Tensor | None = None  # per pose, of the learned stage's validation poses [m]
    diagnosis: object | None = None  # torchcal.pipeline.loop.Diagnosis of the auto method
    filter: object | None = None  # torchcal.pipeline.integrated.IntegratedFilter of the integrated method
    split: S.Split | None = None  # the held-out split, with its revisit groups
    screening: object | None = None  # torchcal.estimate.robust.Screening: the gross errors left out
    holdout_guard: dict | None = None  # the auto method's held-out guard (torchcal.pipeline.loop.guard_holdout)

    @property
    def train(self) -> Measurements:
        return self.data.subset(self.train_idx)

    @property
    def hold(self) -> Measurements:
        return self.data.subset(self.holdout_idx)

    @property
    def fitted_and_held_out(self) -> Measurements:
        """The training samples, then the held-out ones (time order on a trajectory): what a refit uses."""
        return self.data.subset(torch.cat([self.train_idx, self.holdout_idx]))

    def add_stage(self, name: str) -> Stage:
        """Append the model as it stands as stage ``name``, with its held-out and training errors."""
        st = Stage(
            name,
            copy.deepcopy(self.model),
            errors(self.model, self.hold, self.trajectory),
            errors(self.model, self.train, self.trajectory),
        )
        self.stages.append(st)
        return st

    def stage(self, name: str) -> Stage:
        """The first stage called ``name``."""
        return next(s for s in self.stages if s.name == name)

    @property
    def effects_report(self) -> list[dict]:
        """The kept effects as ``report.json`` writes them."""
        return [r.to_dict() for r in self.effects]

    @property
    def rejected(self) -> list[dict]:
        """The rejected candidates as ``report.json`` writes them."""
        return [r.to_dict() for r in self.rejections]


def is_trajectory(m: Measurements, max_step: float = 0.05) -> bool:
    """A continuous trajectory: a non-decreasing ``t`` and consecutive samples close in joint space.

    Static poses are taken one after another too (their ``t`` also grows), but the robot moves
    far between them; along a sampled trajectory the median largest joint step between two
    samples is small (below ``max_step`` rad).
    """
    if m.t is None or m.n < 3 or not bool((torch.diff(m.t) >= 0).all()):
        return False
    steps = torch.diff(m.q, dim=0).abs().max(dim=-1).values
    return float(steps.median()) < max_step


def holdout_split(
    m: Measurements, holdout: float, seed: int, trajectory: bool, group_tol: float = S.GROUP_TOL
) -> S.Split:
    """Training and held-out indices (module docstring): the run's split, also of its training poses."""
    return S.split(m.n, S.holdout_count(m.n, holdout), seed=seed, last=trajectory, q=m.q, group_tol=group_tol)


def min_poses(robot: RobotModel, holdout: float) -> int:
    """Poses needed for a kinematic calibration: 3 observations each, twice the parameters, then the holdout."""
    n_par = int(robot.geometry.mask.sum()) + 9
    return int(math.ceil(2 * n_par / 3 / (1.0 - holdout)))


def _robot(robot: RobotModel | str | os.PathLike, base_link: str | None, tip_link: str | None) -> RobotModel:
    if isinstance(robot, RobotModel):
        return robot
    from torchcal.robot import load_robot  # a spec: the old signature, kept for scripts that pass a name

    return load_robot(robot, base_link=base_link, tip_link=tip_link)


def calibrate(
    robot: RobotModel | str | os.PathLike,
    data: Measurements,
    opts: Options | None = None,
    *,
    robot_spec: str | os.PathLike | None = None,
    base_link: str | None = None,
    tip_link: str | None = None,
) -> CalibrationRun:
    """Run a calibration (module docstring) and return everything the report needs.

    Args:
        robot: the robot, nominal (its instrument pose, lever arm and corrections are overwritten); a built-in
            name or description file is loaded with ``base_link`` and ``tip_link``.
        data: measurements with positions.
        opts: the run's options (default :class:`Options`).
        robot_spec: how the report names the robot's description (default: the spec passed as ``robot``, or the
            robot's source file).
    """
    opts = opts or Options()
    if data.p is None:
        raise OptionError("calibration needs measured positions (x, y, z columns)")
    spec = robot_spec if robot_spec is not None else (robot if not isinstance(robot, RobotModel) else robot.source)
    robot = _robot(robot, base_link, tip_link).to(opts.device)  # the run computes on opts.device
    data = data.to(opts.device)
    if data.dof != robot.dof:
        raise OptionError(f"data have {data.dof} joints but robot '{robot.name}' has {robot.dof}")
    check_poses(data)
    trajectory = is_trajectory(data) if opts.trajectory is None else bool(opts.trajectory)
    if opts.method == "integrated":
        require_trajectory(data, trajectory)
    split = holdout_split(data, opts.holdout, opts.seed + S.Stream.HOLDOUT, trajectory, opts.group_tol)
    tr, ho = split
    tr, ho, screening = screen_gross_errors(robot, data, tr, ho, opts, trajectory)
    model = MeasurementModel(robot)
    run = CalibrationRun(spec, robot, model, opts, data, tr, ho, trajectory, split=split, screening=screening)
    train, hold = run.train, run.hold
    # the calibrated region: what predict and compensate measure extrapolation from; the learned corrections of the
    # methods that add them to a geometry fitted alone fade beyond it (the integrated method's own gates fade its
    # filters, whose geometry may only be right together with their network)
    fade = opts.method in ("auto", "pcm", "kinematic+ann")
    model.set_region(train.q, fade=fade)
    if split.merged_groups:
        run.notes.append(
            f"split: {split.merged_groups} revisited joint configurations ({split.merged_rows} poses) "
            f"kept wholly on one side"
        )

    # 1. the baseline: nominal geometry, tracker pose and lever arm fitted (closed form, then LM)
    _console.info(f"{robot.name}: {train.n} training and {hold.n} held-out poses; fitting tracker pose and lever arm")
    noise = float(train.sigma.median()) if train.sigma is not None else opts.sigma_tracker
    place_instrument_and_tool(robot, train.q, train.p, lever_prior=opts.lever_prior(noise))
    run.fits.append(solve(model, train, ("instrument", "tool"), opts, StageName.NOMINAL, trajectory, identify=False))
    run.add_stage(StageName.NOMINAL)

    # 2. geometry
    if opts.method in ("auto", "kinematic", "kinematic+ann", "integrated"):
        _console.info("kinematic calibration: identifiability analysis and weighted LM")
        run.fits.append(solve(model, train, GEOMETRIC_GROUPS, opts, StageName.GEOMETRIC, trajectory))
        check_corrections(run.fits[-1], model, opts, data)
    run.add_stage(StageName.GEOMETRIC)
    if opts.method == "kinematic" and opts.refits:
        refit_geometry(run, run.fits[-1].identifiability)

    # 2'. the integrated ANN-EKF on the trajectory (network from the training corrections, then the filter)
    if opts.method == "integrated":
        engine = {"auto": integrate_selected, "adaptive": integrate_adaptive, "ekf": integrate}[opts.engine]
        run.filter = engine(run, train, hold)

    # 3. the closed loop: named effects the residuals demand, each refitted jointly and confirmed on validation
    if opts.method == "auto" and opts.diagnose:
        _console.info("diagnosis: score tests of the candidate effects, joint refits, validation")
        # small kernels throughout (u x u solves, one pass over the poses, score tests, smooths): one thread, so that
        # another process on the machine does not multiply the time (torch's threads spin while one waits for a core)
        with torch_threads(1):
            close_loop(run, train, trajectory)

    # 4. a learned residual model where the data demand it
    if opts.method == "auto" and opts.learned:
        _console.info("residual model: kernel regression and correction network judged on validation poses")
        # its fits pin their own threads (the GP's evidence and posterior, the LM refits); the model evaluations between
        # them are small kernels too, so the whole stage runs on one, as the closed loop does
        with torch_threads(1):
            learned_stage(run, train, trajectory)

    # 4'. never worse than the kinematic calibration on the held-out poses (steps back where it would be)
    if opts.method == "auto":
        with torch_threads(1):
            guard_holdout(run, train, trajectory)

    # 3'. the correction network on what remains (paper Eq. 22: corrections in the base frame)
    if opts.method in ("pcm", "kinematic+ann"):
        _console.info(f"correction network 6-{opts.hidden}-3 on the remaining position corrections")
        correction_net_stage(run, train, trajectory)
    # the model written was fitted again on all rows where the run refits; its region is theirs then
    rows = torch.cat([train.q, hold.q]) if opts.refits else train.q
    run.model.set_region(rows, fade=fade)
    run.covariance = _covariance(run)
    return run


def _covariance(run: CalibrationRun) -> ParameterCovariance | None:
    """The parameter covariance of the run's last least-squares fit, for the parameters the final model has (a
    later stage works on a copy of the model: the names are the same)."""
    if not run.fits:
        return None
    last = run.fits[-1]
    cov = ParameterCovariance.from_fit(last.free, last.result)
    params = dict(run.model.named_parameters())
    if cov is None or any(n not in params for n in cov.names):
        return None
    return cov


#: fewest held-out poses a run reports an error on
MIN_HOLDOUT = 3
#: the largest geometric correction, in prior standard deviations, a calibration accepts: lengths and angles
#: (docs/prior_ratios.md: measured on legitimate data, simulated and real, and on data of another robot)
MAX_PRIOR_RATIO = {"m": 50.0, "rad": 300.0}


def check_holdout(n: int, holdout: float) -> None:
    """Refuse a held-out fraction that leaves fewer than :data:`MIN_HOLDOUT` of ``n`` poses: a held-out RMSE of one
    or two poses is no evidence. (The command line's rule; scripts that refit on nearly everything may hold out
    less through the library.)"""
    n_hold = S.holdout_count(n, holdout)
    if n_hold < MIN_HOLDOUT:
        raise OptionError(
            f"--holdout {holdout:g} of {n} poses holds out {n_hold}; at least {MIN_HOLDOUT} are needed for a "
            f"held-out error (--holdout >= {MIN_HOLDOUT / n:.3g})"
        )


def check_poses(data: Measurements) -> None:
    """Refuse poses that cannot determine a calibration, naming the file and the cause, before any fitting: all
    rows with the same joint readings, measured positions that are one point or lie on one line, or only one joint
    moving (its circle leaves the other joints' geometry undetermined)."""
    src = data.source or "the measurements"
    q, p = data.q.detach().cpu(), data.p.detach().cpu()
    spread = q.max(dim=0).values - q.min(dim=0).values
    moving = [f"q{k + 1}" for k in range(data.dof) if float(spread[k]) > S.GROUP_TOL]
    if data.n > 1 and not moving:
        raise MeasurementFileError(
            src,
            f"all {data.n} poses have the same joint readings; a calibration needs the robot measured in many "
            "different poses",
        )
    if data.n > 1 and len(moving) == 1 and data.dof > 1:
        raise MeasurementFileError(
            src,
            f"only {moving[0]} moves across the {data.n} poses; a calibration needs poses that move the joints "
            "together (one joint's circle leaves the rest of the geometry undetermined)",
            column=moving[0],
        )
    if data.n > 2:
        centred = p - p.mean(dim=0)
        sv = torch.linalg.svdvals(centred)
        if float(sv[0]) <= 1e-9 * max(1.0, float(p.abs().max())):
            raise MeasurementFileError(src, f"all {data.n} measured positions x, y, z are the same point")
        if float(sv[1]) <= 1e-9 * float(sv[0]):
            raise MeasurementFileError(
                src,
                f"the {data.n} measured positions x, y, z lie on one straight line; the tracker's pose cannot be "
                "fitted to them (were the columns filled in by hand?)",
            )


def check_corrections(fit: Fit, model: MeasurementModel, opts: Options, data: Measurements) -> None:
    """Stop a run whose geometric corrections are many times their priors (:data:`MAX_PRIOR_RATIO`): the data were
    measured on another robot, in other units, or the description is not the robot's."""
    ratios = prior_ratios(fit, model, opts)
    units = {i.name: i.unit for i in model.robot.parameter_info() if i.group == "geometry"}
    worst = sorted(((r / MAX_PRIOR_RATIO[units[n]], r, n) for n, r in ratios.items()), reverse=True)
    if not worst or worst[0][0] <= 1.0:
        return
    listed = []
    for _, r, n in worst[:3]:
        value = float(fit.result.x[fit.free.names.index(n)])
        shown = f"{value * 1e3:+.4g} mm" if units[n] == "m" else f"{math.degrees(value):+.4g} deg"
        listed.append(f"{n} {shown} ({r:.0f} x its prior)")
    raise EstimationError(
        f"{data.source or 'the measurements'}: the geometric fit of robot '{model.robot.name}' needs corrections "
        f"many times their a-priori size: {', '.join(listed)} (limits: {MAX_PRIOR_RATIO['m']:g} x for lengths, "
        f"{MAX_PRIOR_RATIO['rad']:g} x for angles). Wrong robot (were the data measured on another model?), wrong "
        "units (--length-unit, --angle-unit), or a description that is not this robot's"
    )


def screen_gross_errors(robot: RobotModel, data: Measurements, tr: Tensor, ho: Tensor, opts: Options, trajectory: bool):
    """The training and held-out rows without their gross errors (:func:`torchcal.estimate.robust.screen_geometric`).

    Returns the kept training and held-out indices into ``data`` and the screening (None when
    ``opts.outlier_alpha`` is None). Every later stage sees only the kept rows, and the held-out errors
    leave the rejected held-out rows out; on data without gross errors nothing changes.
    """
    if opts.outlier_alpha is None:
        return tr, ho, None
    from torchcal.estimate.robust import screen_geometric

    _console.info("screening for gross errors: robust geometric fit, data snooping")
    with torch_threads(1):  # small kernels (robust reweighting, u x u solves): one thread, as in close_loop
        sc = screen_geometric(
            MeasurementModel(robot),
            data.subset(tr),
            data.subset(ho),
            opts,
            trajectory=trajectory,
            alpha=opts.outlier_alpha,
        )
    for name, part in (("training", sc.training), ("held-out", sc.holdout)):
        if part.rejected:
            lines = ", ".join(str(r.line) for r in part.rejected[:10]) + (" ..." if len(part.rejected) > 10 else "")
            _console.info(f"{len(part.rejected)} {name} rows rejected as gross errors (file lines {lines})")
    return tr[sc.training.kept.cpu()], ho[sc.holdout.kept.cpu()], sc
