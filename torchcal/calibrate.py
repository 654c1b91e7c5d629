"""Calibration runs: data split, baseline, geometric fit, correction network, held-out errors.

Methods (``--method``):

* ``kinematic``: kinematic calibration (Horvath & Neuner 2024, Eq. 11): the identifiable DH /
  joint-origin errors, the instrument pose and the lever arm, by weighted LM.
* ``pcm``: the paper's position correction model (Eq. 10 + Sec. 2.2): instrument pose and lever
  arm with the nominal geometry, then a :class:`CorrectionNet` on the position corrections.
* ``kinematic+ann``: the literature's sequential "kinCalib+": ``kinematic``, then the network
  on what remains.
* ``auto`` (default): ``kinematic``, then a ``learned`` residual model only where the data demand
  it: a kernel regression (:mod:`torchcal.effects.kernel`) and the correction network are fitted
  on 80 % of the training poses and judged on the other 20 %; the better one is kept when it
  lowers the validation RMSE by at least 5 % and a one-sided paired test gives p < 0.01.

Held-out split: a seeded random 20 % of the poses (static data) or the last 20 % of the
samples (trajectories, see :func:`is_trajectory`), never used for fitting.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import torch

from torchcal import _console
from torchcal.data import Measurements
from torchcal.effects import Context, CorrectionNet, LearnedEffect, MeasurementModel
from torchcal.errors import EstimationError, OptionError
from torchcal.estimate.identifiability import DEFAULT_TOL, Identifiability, analyse, preference_order
from torchcal.estimate.lm import LMResult, global_test, levenberg_marquardt
from torchcal.estimate.netfit import fit_net
from torchcal.estimate.problem import FreeParameters, prior_sigmas, residual_function, whitening
from torchcal.estimate.rigid import fit_instrument_and_tool
from torchcal.robot import load_robot
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor
F64 = torch.float64

METHODS = ("auto", "kinematic", "pcm", "kinematic+ann")
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
    stat_tol: float = 1e-2  # stop LM when a step gains less than 1 % of the variance factor
    net_method: str = "lm"
    net_iterations: int = 100
    trajectory: bool | None = None  # None: decide from a monotonic t column

    def __post_init__(self):
        if self.method not in METHODS:
            raise OptionError(f"method '{self.method}' is not one of {', '.join(METHODS)}")
        if not 0.0 < self.holdout < 0.9:
            raise OptionError(f"holdout must lie in (0, 0.9), got {self.holdout}")


@dataclass
class Fit:
    """One least-squares fit: what was free, the solver's result, the identifiability analysis."""

    stage: str
    result: LMResult
    free: FreeParameters
    identifiability: Identifiability | None = None
    global_test: dict = field(default_factory=dict)


@dataclass
class Stage:
    """A model state with its held-out errors, for the before/after story."""

    name: str
    model: MeasurementModel
    holdout_errors: Tensor  # (N_holdout,) m
    train_errors: Tensor

    @property
    def rmse(self) -> float:
        return rmse(self.holdout_errors)


@dataclass
class CalibrationRun:
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
    effects_report: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)  # candidates that did not earn their place
    notes: list[str] = field(default_factory=list)


def rmse(e: Tensor) -> float:
    return float(e.square().mean().sqrt()) if len(e) else float("nan")


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


def split(m: Measurements, holdout: float, seed: int, trajectory: bool) -> tuple[Tensor, Tensor]:
    """Training and held-out indices (module docstring)."""
    n = m.n
    k = max(1, int(round(holdout * n)))
    if trajectory:
        idx = torch.arange(n)
        return idx[: n - k], idx[n - k :]
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(int(seed)))
    return torch.sort(perm[k:]).values, torch.sort(perm[:k]).values


def errors(model: MeasurementModel, m: Measurements, trajectory: bool) -> Tensor:
    """Norm of the position error per pose ``(N,)`` [m]."""
    with torch.no_grad():
        return (model(Context.from_measurements(m, trajectory=trajectory)) - m.p).norm(dim=-1)


def min_poses(robot: RobotModel, holdout: float) -> int:
    """Poses needed for a kinematic calibration: 3 observations each, twice the parameters, then the holdout."""
    n_par = int(robot.geometry.mask.sum()) + 9
    return int(math.ceil(2 * n_par / 3 / (1.0 - holdout)))


def _selection(model: MeasurementModel, groups: tuple[str, ...], keep: dict[str, bool] | None = None):
    sel, labels = {}, {}
    for g in groups:
        grp = model.robot.groups()[g]
        mask = grp.mask.clone()
        if keep is not None:
            mask &= torch.tensor([keep.get(n, False) for n in grp.names]).reshape(mask.shape)
        sel[f"robot.{g}.delta"] = mask
        labels[f"robot.{g}.delta"] = grp.names
    return sel, labels


def solve(model: MeasurementModel, m: Measurements, groups: tuple[str, ...], opts: Options, stage: str,
          trajectory: bool, identify: bool = True) -> Fit:
    """Weighted LM over the free elements of ``groups`` (identifiable ones only when ``identify``)."""
    ctx = Context.from_measurements(m, trajectory=trajectory)
    W = whitening(model, ctx, m.sigma, opts.sigma_tracker, opts.sigma_joint)
    sel, labels = _selection(model, groups)
    free = FreeParameters(model, sel, labels)
    ida = None
    if identify:
        fun = residual_function(model, free, ctx, m.p, W)
        J = torch.func.jacfwd(fun)(free.vector())
        ida = analyse(J, free.names, preference_order(free.names), tol=opts.rank_tol)
        sel, labels = _selection(model, groups, dict(zip(free.names, ida.free.tolist())))
        free = FreeParameters(model, sel, labels)
    prior = None
    if opts.prior_length is not None and opts.prior_angle is not None and "geometry" in groups:
        units = {i.name: i.unit for i in model.robot.parameter_info() if i.group == "geometry"}
        prior = prior_sigmas(free, units, opts.prior_length, opts.prior_angle)
    fun = residual_function(model, free, ctx, m.p, W, prior)
    res = levenberg_marquardt(fun, free.vector(), names=free.names, max_iter=opts.max_iter, stat_tol=opts.stat_tol)
    if res.status in ("diverged", "failed_solve"):
        raise EstimationError(f"{stage}: least squares {res.status}: {res.message}")
    free.assign(res.x)
    return Fit(stage, res, free, ida, global_test(res))


def _clone(model: MeasurementModel) -> MeasurementModel:
    return copy.deepcopy(model)


def calibrate(robot_spec: str, data: Measurements, opts: Options | None = None, *, base_link: str | None = None,
              tip_link: str | None = None) -> CalibrationRun:
    """Run a calibration (module docstring) and return everything the report needs."""
    opts = opts or Options()
    if data.p is None:
        raise OptionError("calibration needs measured positions (x, y, z columns)")
    robot = load_robot(robot_spec, base_link=base_link, tip_link=tip_link)
    if data.dof != robot.dof:
        raise OptionError(f"data have {data.dof} joints but robot '{robot.name}' has {robot.dof}")
    trajectory = is_trajectory(data) if opts.trajectory is None else bool(opts.trajectory)
    tr, ho = split(data, opts.holdout, opts.seed, trajectory)
    train, hold = data.subset(tr), data.subset(ho)
    model = MeasurementModel(robot)
    run = CalibrationRun(robot_spec, robot, model, opts, data, tr, ho, trajectory)

    def record(name):
        run.stages.append(Stage(name, _clone(model), errors(model, hold, trajectory), errors(model, train, trajectory)))

    # 1. the baseline: nominal geometry, tracker pose and lever arm fitted (closed form, then LM)
    _console.info(f"{robot.name}: {train.n} training and {hold.n} held-out poses; fitting tracker pose and lever arm")
    with torch.no_grad():
        T, lever, _ = fit_instrument_and_tool(robot(train.q), train.p)
        robot.instrument.set_matrix(T)
        robot.tool.nominal.copy_(lever)
    run.fits.append(solve(model, train, ("instrument", "tool"), opts, "nominal", trajectory, identify=False))
    record("nominal")

    # 2. geometry
    if opts.method in ("auto", "kinematic", "kinematic+ann"):
        _console.info("kinematic calibration: identifiability analysis and weighted LM")
        run.fits.append(solve(model, train, ("geometry", "instrument", "tool"), opts, "geometric", trajectory))
    record("geometric")

    # 3. a learned residual model where the data demand it
    if opts.method == "auto":
        _console.info("residual model: kernel regression and correction network judged on validation poses")
        if select_learned(run, train, trajectory):
            record("learned")
            run.effects_report[-1]["rmse_before_mm"] = run.stages[-2].rmse * 1e3
            run.effects_report[-1]["rmse_after_mm"] = run.stages[-1].rmse * 1e3

    # 3'. the correction network on what remains (paper Eq. 22: corrections in the base frame)
    if opts.method in ("pcm", "kinematic+ann"):
        _console.info(f"correction network 6-{opts.hidden}-3 on the remaining position corrections")
        fit_correction_net(run, train, trajectory)
        record("learned")
        s_before, s_after = run.stages[-2], run.stages[-1]
        run.effects_report.append({
            "kind": "learned", "joint": None,
            "params": {"hidden": opts.hidden, "n_weights": model.effects[-1].net.n_weights,
                       "fit": opts.net_method},
            "evidence": {"validation": "early stopping on a seeded 20 % of the training poses"},
            "rmse_before_mm": s_before.rmse * 1e3, "rmse_after_mm": s_after.rmse * 1e3,
        })
    return run


def corrections(model: MeasurementModel, m: Measurements, trajectory: bool) -> Tensor:
    """What the model misses, in the robot base frame ``(N, 3)`` [m] (paper Eq. 22)."""
    with torch.no_grad():
        pred = model(Context.from_measurements(m, trajectory=trajectory))
        return (m.p - pred) @ model.robot.T_tracker_base()[:3, :3]


def select_learned(run: CalibrationRun, train: Measurements, trajectory: bool, min_gain: float = 0.05,
                   alpha: float = 0.01) -> bool:
    """Add the better of a kernel correction and a correction network if it earns its place (module docstring)."""
    from torchcal.effects.kernel import fit_kernel_correction, paired_improvement

    model, opts = run.model, run.options
    corr = corrections(model, train, trajectory)
    perm = torch.randperm(train.n, generator=torch.Generator().manual_seed(int(opts.seed) + 2))
    n_val = max(3, int(0.2 * train.n))
    fi, va = perm[n_val:], perm[:n_val]
    e0 = corr[va].norm(dim=-1)

    kern, info = fit_kernel_correction(model.robot, train.q[fi], corr[fi], q_val=train.q[va], y_val=corr[va],
                                       seed=opts.seed)
    net = CorrectionNet(model.robot.dof, opts.hidden)
    net.reset_parameters(torch.Generator().manual_seed(int(opts.seed) + 3), gain=0.5)
    res = fit_net(net, train.q[fi], corr[fi], val=(train.q[va], corr[va]), method=opts.net_method,
                  iterations=opts.net_iterations)
    with torch.no_grad():
        e_net = (corr[va] - net(train.q[va])).norm(dim=-1)
    candidates = {
        "kernel": (kern, info["val_errors"], kern.describe()),
        "network": (LearnedEffect(net), e_net, {"model": "network", "hidden": opts.hidden, "n_weights": net.n_weights,
                                                "fit": res.method, "best_iteration": res.best_iteration}),
    }
    name = min(candidates, key=lambda k: rmse(candidates[k][1]))
    effect, e1, params = candidates[name]
    rmse0, rmse1 = rmse(e0), rmse(e1)
    test = paired_improvement(e0, e1)
    evidence = {"candidates_validation_rmse_mm": {k: rmse(v[1]) * 1e3 for k, v in candidates.items()},
                "chosen": name, "validation_rmse_before_mm": rmse0 * 1e3, "validation_rmse_after_mm": rmse1 * 1e3,
                "relative_gain": 1.0 - rmse1 / rmse0 if rmse0 > 0 else 0.0, **test,
                "rule": f"relative gain >= {min_gain:.0%} and p < {alpha}", "n_validation": int(n_val)}
    accepted = evidence["relative_gain"] >= min_gain and test["p_value"] < alpha
    run.notes.append(f"learned residual model: {name} {'accepted' if accepted else 'rejected'} "
                     f"(validation {rmse0 * 1e3:.4f} -> {rmse1 * 1e3:.4f} mm, p = {test['p_value']:.2g})")
    if not accepted:
        run.rejected.append({"kind": "learned", "joint": None, "evidence": evidence})
        return False
    model.add(effect)
    run.effects_report.append({"kind": "learned", "joint": None, "params": params, "evidence": evidence})
    return True


def fit_correction_net(run: CalibrationRun, train: Measurements, trajectory: bool) -> None:
    """Add a :class:`LearnedEffect` fitted to the training corrections, early-stopped on a validation share."""
    model, opts = run.model, run.options
    ctx = Context.from_measurements(train, trajectory=trajectory)
    with torch.no_grad():
        pred = model(ctx)
        R = model.robot.T_tracker_base()[:3, :3]
        corr = (train.p - pred) @ R  # R^T (y - f): the correction in the base frame
    g = torch.Generator().manual_seed(int(opts.seed) + 1)
    perm = torch.randperm(train.n, generator=g)
    n_val = max(1, int(0.2 * train.n))
    fit_i, val_i = perm[n_val:], perm[:n_val]
    net = CorrectionNet(model.robot.dof, opts.hidden)
    net.reset_parameters(g, gain=0.5)
    res = fit_net(net, train.q[fit_i], corr[fit_i], val=(train.q[val_i], corr[val_i]), method=opts.net_method,
                  iterations=opts.net_iterations, generator=g)
    run.notes.append(f"correction network: {res.method} {res.status} after {res.iterations} iterations, "
                     f"best validation at {res.best_iteration}")
    model.add(LearnedEffect(net))
