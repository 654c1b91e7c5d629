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
  trajectory (:mod:`torchcal.filter.integrated`): by default the adaptive filter with the geometry in its
  state (``engine="adaptive"``), or the paper's filter on the kinematic geometry (``engine="ekf"``).

Held-out split: a seeded random 20 % of the poses (static data) or the last 20 % of the
samples (trajectories, see :func:`is_trajectory`), never used for fitting.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace

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

METHODS = ("auto", "kinematic", "pcm", "kinematic+ann", "integrated")
DEFAULT_METHOD = "auto"
#: engines of the integrated method (torchcal.filter.integrated)
ENGINES = ("auto", "adaptive", "ekf")


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
    diagnose: bool = True  # auto: search the named effects (the closed loop) before the learned stage
    alpha: float = 0.01  # closed loop: family-wise level of the score tests (Bonferroni)
    alpha_validation: float = 0.05  # closed loop: level of the paired validation test
    engine: str = "auto"  # integrated: "auto" (chosen on validation, geometry alone included), "adaptive"
    # (geometry in the filter state) or "ekf" (the paper's filter)

    def __post_init__(self):
        if self.method not in METHODS:
            raise OptionError(f"method '{self.method}' is not one of {', '.join(METHODS)}")
        if self.engine not in ENGINES:
            raise OptionError(f"engine '{self.engine}' is not one of {', '.join(ENGINES)}")
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
    whitening: Tensor | None = None  # (N, 3, 3) the L_i^-1 the residuals were whitened with


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
    learned_validation_errors: Tensor | None = None  # per pose, of the learned stage's validation poses [m]
    diagnosis: object | None = None  # torchcal.diagnose.Diagnosis of the auto method
    filter: object | None = None  # torchcal.filter.integrated.IntegratedFilter of the integrated method


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


#: effect kinds whose parameters the least-squares fit estimates jointly with the geometry
NAMED_KINDS = ("compliance", "backlash", "cyclic", "drift")


def effect_parameter_labels(model: MeasurementModel) -> tuple[dict[str, Tensor], dict[str, list[str]]]:
    """Selection masks (all free) and element names of the named effects' parameters, e.g.
    ``effects.0.k`` -> ``["compliance(joint 2).k"]``."""
    sel, labels = {}, {}
    for i, e in enumerate(model.effects):
        if e.kind not in NAMED_KINDS:
            continue
        for pname, p in e.named_parameters(recurse=False):
            key = f"effects.{i}.{pname}"
            sel[key] = torch.ones(p.shape, dtype=torch.bool)
            n = p.numel()
            labels[key] = [f"{e.label()}.{pname}" + (f"[{k}]" if n > 1 else "") for k in range(n)]
    return sel, labels


def _selection(model: MeasurementModel, groups: tuple[str, ...], keep: dict[str, bool] | None = None,
               effects: bool = False):
    sel, labels = {}, {}
    for g in groups:
        grp = model.robot.groups()[g]
        mask = grp.mask.clone()
        if keep is not None:
            mask &= torch.tensor([keep.get(n, False) for n in grp.names]).reshape(mask.shape)
        sel[f"robot.{g}.delta"] = mask
        labels[f"robot.{g}.delta"] = grp.names
    if effects:
        esel, elab = effect_parameter_labels(model)
        for key, mask in esel.items():
            if keep is not None:
                mask = torch.tensor([keep.get(n, True) for n in elab[key]]).reshape(mask.shape)
            sel[key], labels[key] = mask, elab[key]
    return sel, labels


def solve(model: MeasurementModel, m: Measurements, groups: tuple[str, ...], opts: Options, stage: str,
          trajectory: bool, identify: bool = True, effects: bool = False,
          identifiability: Identifiability | None = None) -> Fit:
    """Weighted LM over the free elements of ``groups`` (identifiable ones only when ``identify``).

    With ``effects`` the parameters of the model's named effects (:data:`NAMED_KINDS`) are estimated
    jointly with the groups; in the identifiability analysis they come after the geometry, so an effect
    parameter that the geometry already explains is held at its current value.

    ``identifiability`` reuses an earlier analysis (that of the geometric fit) for the robot's
    parameters instead of analysing again: after a fit the nominally parallel axes of a UR arm are no
    longer exactly parallel, and a new analysis would free parameters that are only determined to
    1e-5 (``d3``, ``d4``), which turns the refit into a crawl along a flat valley.
    """
    ctx = Context.from_measurements(m, trajectory=trajectory)
    W = whitening(model, ctx, m.sigma, opts.sigma_tracker, opts.sigma_joint)
    sel, labels = _selection(model, groups, effects=effects)
    free = FreeParameters(model, sel, labels)
    ida = None
    if identifiability is not None:
        ida = identifiability
        keep = dict(zip(ida.names, ida.free.tolist()))
        keep.update({n: True for n in free.names if n not in keep})  # effect parameters: checked when scored
        sel, labels = _selection(model, groups, keep, effects=effects)
        free = FreeParameters(model, sel, labels)
    elif identify:
        fun = residual_function(model, free, ctx, m.p, W)
        J = torch.func.jacfwd(fun)(free.vector())
        ida = analyse(J, free.names, preference_order(free.names), tol=opts.rank_tol)
        sel, labels = _selection(model, groups, dict(zip(free.names, ida.free.tolist())), effects=effects)
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
    return Fit(stage, res, free, ida, global_test(res), W)


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
    if opts.method == "integrated":
        from torchcal.filter.integrated import require_trajectory

        require_trajectory(data, trajectory)
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
    if opts.method in ("auto", "kinematic", "kinematic+ann", "integrated"):
        _console.info("kinematic calibration: identifiability analysis and weighted LM")
        run.fits.append(solve(model, train, ("geometry", "instrument", "tool"), opts, "geometric", trajectory))
    record("geometric")

    # 2'. the integrated ANN-EKF on the trajectory (network from the training corrections, then the filter)
    if opts.method == "integrated":
        from torchcal.filter.integrated import integrate, integrate_adaptive, integrate_selected

        engine = {"auto": integrate_selected, "adaptive": integrate_adaptive, "ekf": integrate}[opts.engine]
        run.filter = engine(run, train, hold, record)

    # 3. the closed loop: named effects the residuals demand, each refitted jointly and confirmed on validation
    if opts.method == "auto" and opts.diagnose:
        from torchcal.diagnose import close_loop

        _console.info("diagnosis: score tests of the candidate effects, joint refits, validation")
        close_loop(run, train, trajectory, record, alpha=opts.alpha, alpha_val=opts.alpha_validation)

    # 4. a learned residual model where the data demand it
    if opts.method == "auto":
        _console.info("residual model: kernel regression and correction network judged on validation poses")
        if select_learned(run, train, trajectory):
            e_val = refine_learned(run, train, trajectory)
            if any(e.kind in NAMED_KINDS for e in model.effects):
                prune_named(run, train, trajectory, e_val)
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
    fi, va = _learned_split(train, opts.seed)
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
                "rule": f"relative gain >= {min_gain:.0%} and p < {alpha}", "n_validation": len(va)}
    accepted = evidence["relative_gain"] >= min_gain and test["p_value"] < alpha
    run.notes.append(f"learned residual model: {name} {'accepted' if accepted else 'rejected'} "
                     f"(validation {rmse0 * 1e3:.4f} -> {rmse1 * 1e3:.4f} mm, p = {test['p_value']:.2g})")
    if not accepted:
        run.rejected.append({"kind": "learned", "joint": None, "evidence": evidence})
        return False
    model.add(effect)
    run.learned_validation_errors = e1
    run.effects_report.append({"kind": "learned", "joint": None, "name": "learned", "label": "learned",
                               "params": params, "evidence": evidence})
    return True


#: LM iterations of a refit with the learned model in place (:func:`_refit_with_learned`)
REFIT_MAX_ITER = 10


def _learned_split(train: Measurements, seed: int) -> tuple[Tensor, Tensor]:
    """The fitting and validation poses of the learned stage (as in :func:`select_learned`)."""
    perm = torch.randperm(train.n, generator=torch.Generator().manual_seed(int(seed) + 2))
    n_val = max(3, int(0.2 * train.n))
    return perm[n_val:], perm[:n_val]


def _refit_with_learned(run: CalibrationRun, model: MeasurementModel, train: Measurements, trajectory: bool):
    """One alternating round on ``model`` (its last effect is the learned one): the geometry and the named
    effects with the learned correction in place, then the learned model on the new corrections.

    Returns the least-squares fit and the learned model's validation errors per pose ``(n_val,)`` [m];
    a refitted kernel replaces the old one in ``model``.
    """
    from torchcal.effects.kernel import fit_kernel_correction

    opts = run.options
    index = len(model.effects) - 1
    eff = model.effects[index]
    fi, va = _learned_split(train, opts.seed)
    ida = next((f.identifiability for f in reversed(run.fits) if f.identifiability is not None), None)
    groups = ("geometry", "instrument", "tool") if ida is not None else ("instrument", "tool")
    # warm-started from the current fit and used to compare models, the refit needs few iterations; on real
    # data its valley is flat and an uncapped LM crawls for minutes without changing the comparison
    fit = solve(model, train, groups, replace(opts, max_iter=min(opts.max_iter, REFIT_MAX_ITER)),
                "learned (alternating refit)", trajectory, effects=True, identifiability=ida)
    others = MeasurementModel(model.robot, [e for i, e in enumerate(model.effects) if i != index])
    corr = corrections(others, train, trajectory)
    if isinstance(eff, LearnedEffect):
        fit_net(eff.net, train.q[fi], corr[fi], val=(train.q[va], corr[va]), method=opts.net_method,
                iterations=opts.net_iterations, ftol=1e-6)
        with torch.no_grad():
            e_val = (corr[va] - eff.net(train.q[va])).norm(dim=-1)
    else:
        new, info = fit_kernel_correction(model.robot, train.q[fi], corr[fi], q_val=train.q[va], y_val=corr[va],
                                          seed=opts.seed)
        model.effects[index] = new
        e_val = info["val_errors"]
    return fit, e_val


def refine_learned(run: CalibrationRun, train: Measurements, trajectory: bool, rounds: int = 3) -> Tensor:
    """Refit the geometry (and the named effects) and the learned model in turn, while validation improves.

    The geometric fit has already bent the geometry towards the part of the non-geometric field
    that looks geometric, and the learned model was fitted to what was left. Alternating the two
    fits (geometry with the learned correction in place, then the learned model on the new
    corrections, on the same fitting and validation poses as :func:`select_learned`) moves the
    pair towards their joint least-squares solution; a round is kept only when the validation
    RMSE of the learned model falls. Returns the learned model's validation errors per pose.
    """
    model = run.model
    best = run.effects_report[-1]["evidence"]["validation_rmse_after_mm"] * 1e-3
    best_e = None
    history = [best * 1e3]
    for _ in range(rounds):
        trial = copy.deepcopy(model)
        fit, e_val = _refit_with_learned(run, trial, train, trajectory)
        v = rmse(e_val)
        if not v < best * (1.0 - 1e-3):
            break
        _adopt(model, trial)
        best, best_e = v, e_val
        history.append(v * 1e3)
        run.fits.append(fit)
    if best_e is None:  # no round helped: the errors of the model as it stands
        best_e = run.learned_validation_errors
    run.effects_report[-1]["evidence"]["alternating_refit_validation_rmse_mm"] = history
    run.notes.append(f"learned residual model: {len(history) - 1} alternating refits of geometry and learned model, "
                     f"validation {history[0]:.4f} -> {history[-1]:.4f} mm")
    return best_e


def _adopt(model: MeasurementModel, other: MeasurementModel) -> None:
    """Make ``model`` hold ``other``'s effects and parameter values (the robot stays the same object)."""
    model.robot.load_state_dict(other.robot.state_dict())
    model.effects = torch.nn.ModuleList(list(other.effects))
    for e in model.effects:
        e.train(False)


def prune_named(run: CalibrationRun, train: Measurements, trajectory: bool, e_val: Tensor) -> None:
    """With a learned model in place, drop each named effect the learned model explains as well.

    A smooth field that no named effect describes still projects onto some of their regressors,
    and the loop may accept one for that share. For each named effect in turn, the model without
    it (geometry and learned model refitted as in :func:`refine_learned`) is compared with the
    model with it on the learned stage's validation poses: the effect stays only when the model
    with it is better by a one-sided paired test at ``alpha_validation``.
    """
    from torchcal.effects.kernel import paired_improvement

    model, opts = run.model, run.options
    for label in [e.label() for e in model.effects if e.kind in NAMED_KINDS]:
        k = next(i for i, e in enumerate(model.effects) if e.label() == label)
        eff = model.effects[k]
        trial = copy.deepcopy(model)
        del trial.effects[k]
        fit, e_without = _refit_with_learned(run, trial, train, trajectory)
        test = paired_improvement(e_without, e_val)
        evidence = {"validation_rmse_with_mm": rmse(e_val) * 1e3, "validation_rmse_without_mm": rmse(e_without) * 1e3,
                    "z": test["z"], "p_value": test["p_value"], "n": test["n"],
                    "rule": f"kept when the model with it is better, one-sided paired p < {opts.alpha_validation}"}
        entry = next((r for r in run.effects_report if r.get("label") == eff.label()), None)
        if entry is not None:
            entry["evidence"]["with_learned_model"] = evidence
        if test["p_value"] < opts.alpha_validation:
            continue
        _adopt(model, trial)
        run.fits.append(fit)
        e_val = e_without
        reason = (f"the learned model explains it as well (validation {evidence['validation_rmse_with_mm']:.4f} mm "
                  f"with it, {evidence['validation_rmse_without_mm']:.4f} mm without, p = {test['p_value']:.2g})")
        run.notes.append(f"diagnosis: {eff.label()} dropped: {reason}")
        if entry is not None:
            run.effects_report.remove(entry)
            run.rejected.append({"kind": entry["kind"], "joint": entry["joint"], "name": entry.get("name"),
                                 "reason": f"accepted in round {entry['evidence'].get('round')}, then dropped: "
                                           f"{reason}", "evidence": entry["evidence"]})
        run.stages[:] = [st for st in run.stages if st.name != eff.label()]
        if run.diagnosis is not None:
            for d in run.diagnosis.decisions:
                if d.stage == eff.label():
                    d.reason += f"; dropped after the learned stage: {reason}"


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
