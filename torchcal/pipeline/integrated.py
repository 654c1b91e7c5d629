"""The ``integrated`` calibration method: the integrated ANN-EKF of Horvath & Neuner (2024) on a trajectory.

Two engines (``Options.engine``, ``--engine``): ``adaptive`` (the default, :func:`integrate_adaptive`) puts the
identifiable geometry into the filter state with a fixed random-feature network (the paper's future work,
:mod:`torchcal.filter.adaptive`); ``ekf`` (:func:`integrate`) is the paper's filter on the geometry of the
kinematic calibration, described below.

The paper (Sec. 2.3, Fig. 10) keeps the kinematic model in the filter's system equation and the correction
network in its observation equation, and filters a continuous trajectory sample by sample. It needs the
geometry, the instrument pose and the lever arm to be known, and network weights close to the final ones
(Sec. 3.2: within 10 %). On measured data neither is given, so the method runs in five steps:

1. kinematic calibration on the training part, as the ``kinematic`` method does (the ``geometric`` stage);
2. the network initialised by an LM fit to the training corrections of that geometry (the position
   correction model; the paper's own suggestion in Sec. 4 for the initialisation problem);
3. a joint LM refinement of geometry, instrument pose, lever arm and network weights on the training part:
   the batch form of the simultaneous estimation the paper aims at. The kinematic calibration of step 1 has
   taken the share of the non-geometric field that looks geometric into the geometry, and a network fitted
   to what is left extrapolates badly (with the *true* geometry the same network fit extrapolates several times
   better, ``scripts/integrated_trajectory.py``); estimating both together can move
   that share back, but it can also make things worse, so the last 10 % of the training samples judge it
   after every restart and the best state (possibly the unrefined start) is kept;
4. the EKF pass over the training samples (:class:`~torchcal.filter.EKFTrainer`) from the refined weights,
   the probe position pinned to the refined kinematics (the geometry is estimated already, and the filter
   cannot estimate it -- the paper leaves that "adaptive" step to future work, and so do we), the weights a
   slow random walk (stochastic model: the constants below);
5. the test phase: the held-out last 20 % of the trajectory, predicted without updates.

The paper's ANN re-iteration (Fig. 10: an LM re-fit every 500 samples to the corrections of Eq. 22, taken
against the filter's own geometric state, without a validation share) is off by default
(``reiterate_every=0``; the argument switches it on): on measured data, re-fitting to the filter's own
corrections without a validation share raised the held-out error several-fold in our trials, and each pass
costs an LM fit every 500 samples.

The final model is the refined geometry plus a :class:`~torchcal.effects.LearnedEffect` with the filter's
last weights; ``torchcal predict`` reloads it, and its held-out error is the ``integrated`` stage. The
filter's own test-phase prediction (last filtered state moved by the relative kinematics, Eq. 15) differs
from it by the offset of the last filtered state from the kinematics; report.json gives both, and the
held-out error after each step.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from torchcal import _console
from torchcal import stats as S
from torchcal.data import Measurements
from torchcal.effects import Context, CorrectionNet, LearnedEffect, MeasurementModel
from torchcal.effects import support as sup
from torchcal.errors import EstimationError, OptionError
from torchcal.estimate.fit import GEOMETRIC_GROUPS, errors, place_instrument_and_tool, solve
from torchcal.estimate.lm import LMResult, levenberg_marquardt
from torchcal.estimate.problem import FreeParameters, prior_sigmas, residual_function, whitening
from torchcal.filter.ekf import EKFConfig, EKFResult, EKFTrainer
from torchcal.pipeline.records import EffectRecord, Rejection, StageName

if TYPE_CHECKING:  # the run imports this module: only the type, no import at run time
    from torchcal.pipeline.run import CalibrationRun

Tensor = torch.Tensor

#: the filter's stochastic model in the integrated method (step 4). The weights: a-priori sigma 0.05 in the
#: network's mm units and a slow random walk of 1e-3 per sample, so that the network follows the newest samples,
#: which the held-out ones continue. The probe position: pinned to the refined kinematics (20 um a-priori, 1 nm
#: per step). The joint reading noise of a sample enters the relative prediction (Eq. 15) of two consecutive
#: steps with opposite signs, so it does not accumulate: it goes into the observation noise here, not into the
#: process noise of Eq. 19, where it would let the position wander off the kinematics step by step.
#: ``scripts/integrated_trajectory.py --engine ekf`` measures this stochastic model against fixed weights.
SIGMA_W0 = 0.05
Q_W = 1e-3
SIGMA_T0 = 2e-5
Q_T = 1e-9
#: LM iterations of the joint refinement of geometry and network (step 3), restarted with a fresh damping every
#: JOINT_RESTART iterations: the fit crawls along the valley where geometry and network trade places, and a
#: damping that grew in its curved stretches otherwise keeps the later steps short
JOINT_ITERATIONS = 150
JOINT_RESTART = 10
#: the joint refinement uses every JOINT_STRIDE-th training sample: neighbouring samples of a trajectory carry
#: nearly the same information, and the thinned set keeps an iteration cheap
JOINT_STRIDE = 3
#: the last FORWARD_FRACTION of the training samples judge the joint refinement, after each restart, against
#: not refining at all (neither the network's initial fit nor the refinement sees them; the geometry refit and
#: the filter do): the held-out samples continue the trajectory, so the state that predicts the *next* stretch
#: best is kept, not the one that interpolates a random share best
FORWARD_FRACTION = 0.1


def _first_draw(name: str) -> property:
    """The filter result's ``name`` ``(N, 3)`` [m] of its only draw: an integrated run makes one pass."""
    return property(lambda self: getattr(self.result, name)[0], doc=f"The filter's {name} per sample (N, 3) [m].")


@dataclass
class IntegratedFilter:
    """The filter pass of an ``integrated`` run, with the references the report compares it with.

    All per-sample tensors cover the training samples, then the held-out ones ``(N, 3)`` [m], tracker frame.
    """

    result: EKFResult  # the pass (draw dimension 1)
    y: Tensor  # measured positions
    kinematic: Tensor  # prediction of the calibrated kinematic model alone
    n_train: int
    config: EKFConfig
    w_start: Tensor  # the weights the filter started from (after steps 2-3)
    weight_cov: Tensor | None = None  # final covariance of the weights in the filter's state (k, k)
    weight_index: Tensor | None = None  # their indices in the network's flat weights (k,)

    geometric = _first_draw("geometric")
    nongeometric = _first_draw("nongeometric")
    prediction = _first_draw("prediction")

    def deviations(self) -> dict[str, Tensor]:
        """``devG``, ``devNG``, ``devAll`` per sample ``(N, 3)`` [m] (the paper's Figs. 9 and 11 on measured data).

        Without a truth, the measurement is split at the calibrated kinematic model: geometric reference
        ``G = T p(theta)``, non-geometric reference ``NG = y - G``. Then ``devG = G_filter - G``,
        ``devNG = NG_filter - NG`` and ``devAll = devG + devNG = prediction - y`` (tracker noise included).
        """
        G, NG = self.kinematic, self.y - self.kinematic
        return {"devG": self.geometric - G, "devNG": self.nongeometric - NG, "devAll": self.prediction - self.y}


def require_trajectory(data: Measurements, trajectory: bool) -> None:
    """Raise :class:`OptionError` unless ``data`` is a continuous trajectory with a monotonic ``t`` column."""
    where = f"{data.source}: " if data.source else ""
    other = "use --method kinematic, kinematic+ann or auto for static poses"
    if data.t is None:
        raise OptionError(
            f"{where}method 'integrated' needs a continuous trajectory with a monotonic t column "
            f"(acquisition time, s), and the data have no t column; {other}"
        )
    steps = torch.diff(data.t)
    if bool((steps < 0).any()):
        k = int(torch.nonzero(steps < 0)[0])
        line = data.lines[k + 1] if data.lines else k + 2
        raise OptionError(
            f"{where}method 'integrated' needs a monotonic t column, but t decreases at line {line} "
            f"({float(data.t[k]):g} -> {float(data.t[k + 1]):g} s)"
        )
    if not trajectory:
        jump = torch.diff(data.q, dim=0).abs().max(dim=-1).values.median() if data.n > 1 else float("nan")
        raise OptionError(
            f"{where}method 'integrated' needs a continuous trajectory, but consecutive samples lie "
            f"far apart in joint space (median largest joint step {float(jump):.3g} rad, a trajectory "
            f"has < 0.05): these look like static poses; {other}"
        )


def filter_config(
    model: MeasurementModel, data: Measurements, sigma_tracker: float, sigma_joint: float, reiterate_every: int
) -> EKFConfig:
    """The filter's configuration for an integrated run (module constants and the run's stochastic model).

    The observation sigma per axis combines the tracker's (the median per-point ``sx, sy, sz`` when the data
    have them) with the joint noise at the probe, ``sigma_joint * |J_q|_F / sqrt(3)`` (median over the samples).
    """
    if data.sigma is not None:
        sigma_tracker = float(data.sigma.median())
    with torch.no_grad():
        _, Jq = model.robot.probe_jacobian(data.q)
    joint_at_probe = sigma_joint * float(Jq.flatten(-2).norm(dim=-1).median()) / math.sqrt(3.0)
    return EKFConfig(
        sigma_w0=SIGMA_W0,
        q_w=Q_W,
        sigma_t0=SIGMA_T0,
        q_t=Q_T,
        sigma_joint=0.0,
        sigma_tracker=math.hypot(sigma_tracker, joint_at_probe),
        reiterate_every=reiterate_every,
    )


def integrate(
    run: CalibrationRun,
    train: Measurements,
    hold: Measurements,
    *,
    joint_iterations: int = JOINT_ITERATIONS,
    reiterate_every: int = 0,
    pcm_iterations: int | None = None,
) -> IntegratedFilter:
    """Steps 2-5 of the module docstring on a run whose geometric stage is done; adds the ``integrated`` stage.

    Args:
        run: the :class:`~torchcal.pipeline.run.CalibrationRun` (its model holds the calibrated geometry and no
            effects yet).
        train, hold: the training samples and the held-out last samples of the trajectory, in time order.
        joint_iterations: LM iterations of the joint refinement (0: none).
        reiterate_every: the paper's ANN re-iteration period in samples (0, the default: none; module docstring).
        pcm_iterations: LM iterations of the network's initial fit (default ``run.options.net_iterations``).
    """
    model, robot, opts = run.model, run.model.robot, run.options
    cfg = filter_config(model, train, opts.sigma_tracker, opts.sigma_joint, reiterate_every)
    net = CorrectionNet(robot.dof, opts.hidden, device=robot.device)
    net.reset_parameters(torch.Generator().manual_seed(int(opts.seed) + S.Stream.NETWORK_INIT), gain=0.5)
    trainer = EKFTrainer(robot, net, cfg)
    steps = {}
    _console.info(
        f"integrated ANN-EKF: network {robot.dof}-{opts.hidden}-3 initialised by LM on the training corrections"
    )
    n_fit = train.n - max(1, int(round(FORWARD_FRACTION * train.n)))
    fit, forward = train.subset(slice(0, n_fit)), train.subset(slice(n_fit, None))
    net.set_flat(
        trainer.pcm_weights(
            fit.q, fit.p, net.flat(), iterations=pcm_iterations or opts.net_iterations, seed=int(opts.seed)
        )
    )
    model.add(LearnedEffect(net))
    steps["initial_network"] = _rmse(_errors(model, hold))
    ida = next((f.identifiability for f in reversed(run.fits) if f.identifiability is not None), None)
    joint_info = None
    if joint_iterations > 0:
        _console.info(
            f"integrated ANN-EKF: geometry, instrument, lever arm and network refined jointly "
            f"(up to {joint_iterations} LM iterations, judged on the last {forward.n} training samples)"
        )
        joint, joint_info = refine_jointly(
            model, fit.subset(slice(None, None, JOINT_STRIDE)), ida, opts, joint_iterations, validation=forward
        )
        joint_info["status"] = joint.status
        steps["joint_refinement"] = _rmse(_errors(model, hold))
    # the geometry's final least-squares fit with the network in place: its statistics go into the report
    run.fits.append(
        solve(
            model,
            train,
            GEOMETRIC_GROUPS,
            opts,
            "integrated (geometry with the network in place)",
            True,
            identifiability=ida,
        )
    )
    steps["geometry_refit"] = _rmse(_errors(model, hold))

    _console.info(f"integrated ANN-EKF: filtering {train.n} samples, then predicting {hold.n} held-out ones")
    q = torch.cat([train.q, hold.q])
    # the held-out positions never reach the filter: NaN where the test phase would not read them anyway
    y_in = torch.cat([train.p, torch.full_like(hold.p, float("nan"))])
    with torch.no_grad():
        kin = robot.probe_position(q)
    res = trainer.run(q, y_in, train.n, net.flat(), t0=kin[0])
    if res.diverged:
        raise EstimationError(f"integrated ANN-EKF: the filter {res.status[0]}")
    nw = net.n_weights  # the paper's state is [w; t]
    filt = IntegratedFilter(
        res, torch.cat([train.p, hold.p]), kin, train.n, cfg, net.flat(), res.P[0, :nw, :nw], torch.arange(nw)
    )
    net.set_flat(res.w[0])  # the final model: calibrated geometry + the filter's last weights
    run.add_stage(StageName.INTEGRATED)
    _record_ekf(run, filt, steps, joint_info, hold, net.n_weights)
    return filt


def _integrated_record(run: CalibrationRun, after, *, params: dict, evidence: dict) -> EffectRecord:
    """The integrated run's effect record (the learned correction, stage ``learned``), with the held-out RMSE of
    the geometric stage before it and of the stage ``after`` it."""
    before = run.stage(StageName.GEOMETRIC)
    return EffectRecord(
        "learned",
        None,
        params,
        evidence,
        name="integrated",
        label="learned",
        rmse_before_mm=before.rmse * 1e3,
        rmse_after_mm=after.rmse * 1e3,
    )


def _record_ekf(
    run: CalibrationRun,
    filt: IntegratedFilter,
    steps: dict,
    joint_info: dict | None,
    hold: Measurements,
    n_weights: int,
) -> None:
    """The ``ekf`` engine's effect record and note: held-out RMSE after each step, the filter's statistics."""
    opts, res, cfg, n_train = run.options, filt.result, filt.config, filt.n_train
    after = run.stages[-1]
    e_filter = (filt.prediction[n_train:] - hold.p).norm(dim=-1)
    nis = res.nis[0, :n_train]
    run.effects.append(
        _integrated_record(
            run,
            after,
            params={
                "model": "network",
                "hidden": opts.hidden,
                "n_weights": n_weights,
                "fit": "integrated ANN-EKF (Horvath & Neuner 2024, Sec. 2.3) after an LM initialisation and a "
                "joint LM refinement with the geometry",
            },
            evidence={
                "holdout_rmse_steps_mm": {k: v * 1e3 for k, v in steps.items()},
                "holdout_rmse_filter_prediction_mm": _rmse(e_filter) * 1e3,
                "joint_refinement": joint_info,
                "filter": {
                    "status": res.status[0],
                    "samples_filtered": n_train,
                    "seconds": res.seconds,
                    "nis_mean": float(nis.mean()),
                    "nis_expected": 3.0,
                    "q_yy_final": float(res.q_yy[0, n_train - 1]),
                    "reiterations": len(res.reiterations),
                    "reiterate_every": cfg.reiterate_every,
                    "sigma_w0": cfg.sigma_w0,
                    "sigma_t0_m": cfg.sigma_t0,
                    "q_w": cfg.q_w,
                    "q_t_m": cfg.q_t,
                    "sigma_observation_m": cfg.sigma_tracker,
                    "final_state_offset_from_kinematics_mm": float((res.t[0] - filt.kinematic[-1]).norm()) * 1e3,
                },
            },
        )
    )
    text = ", ".join(f"{k.replace('_', ' ')} {v * 1e3:.4f}" for k, v in steps.items())
    run.notes.append(
        f"integrated ANN-EKF: held-out RMSE [mm] after {text}, after the filter {after.rmse * 1e3:.4f} "
        f"(final model); the filter's own test-phase prediction {_rmse(e_filter) * 1e3:.4f}; mean NIS "
        f"{float(nis.mean()):.2f} (3 expected)"
    )


def refine_jointly(
    model: MeasurementModel,
    m: Measurements,
    identifiability,
    opts,
    iterations: int,
    validation: Measurements | None = None,
) -> tuple[LMResult, dict]:
    """Weighted LM over the identifiable geometry, the instrument pose, the lever arm and the network's weights.

    With ``validation`` (later samples of the trajectory than ``m``), the parameters after the restart with the
    lowest validation RMSE are kept (none at all included: then the starting values stay); returns the LM
    result and that history.

    The model's last effect must be the :class:`LearnedEffect`. The geometric columns of the Jacobian come
    from ``torch.func.jacfwd`` over the few geometric parameters, the network's from its analytic Jacobian
    (rotated into the tracker frame and whitened), which keeps an iteration cheap with ~300 weights. The
    geometry keeps the run's a-priori sigmas; the weights have none. The normal matrix is singular (a tanh
    network has symmetric weight sets), which LM's damping handles; the result's statistics are not used.
    Steps: :func:`_joint_parameters` (what is free), :func:`_joint_problem` (residuals and Jacobian),
    :func:`_joint_restarts` (LM with restarts, judged on ``validation``).
    """
    free, n_geo = _joint_parameters(model, identifiability)
    fun, jacobian = _joint_problem(model, free, n_geo, m, opts)

    def score(history: list) -> float:
        return _rmse(_errors(model, validation)) if validation is not None else -float(len(history))

    return _joint_restarts(fun, jacobian, free, iterations, score, validation is not None)


def _joint_parameters(model: MeasurementModel, identifiability) -> tuple[FreeParameters, int]:
    """The free parameters of the joint refinement: the identifiable elements of the geometry, instrument and
    tool groups (all of them without an identifiability analysis), then every weight of the model's last effect's
    network; and how many of them are geometric."""
    robot = model.robot
    keep = {} if identifiability is None else dict(zip(identifiability.names, identifiability.free.tolist()))
    sel, labels = {}, {}
    for g in ("geometry", "instrument", "tool"):
        grp = robot.groups()[g]
        mask = grp.mask.clone()
        if identifiability is not None:
            mask &= torch.tensor([keep.get(n, False) for n in grp.names], device=mask.device).reshape(mask.shape)
        sel[f"robot.{g}.delta"], labels[f"robot.{g}.delta"] = mask, grp.names
    n_geo = sum(int(mk.sum()) for mk in sel.values())
    k = len(model.effects) - 1
    for name, p in model.effects[k].net.named_parameters():
        sel[f"effects.{k}.net.{name}"] = torch.ones(p.shape, dtype=torch.bool, device=p.device)
    return FreeParameters(model, sel, labels), n_geo


def _joint_problem(model: MeasurementModel, free: FreeParameters, n_geo: int, m: Measurements, opts):
    """The whitened residual function of the joint refinement (observations, then the geometry's prior rows) and
    its Jacobian: ``jacfwd`` over the geometric columns, the network's analytic Jacobian for the weights."""
    robot, net = model.robot, model.effects[-1].net
    ctx = Context.from_measurements(m, trajectory=True)
    W = whitening(model, ctx, m.sigma, opts.sigma_tracker, opts.sigma_joint)
    prior = None
    if opts.prior_length is not None and opts.prior_angle is not None:
        units = {i.name: i.unit for i in robot.parameter_info() if i.group == "geometry"}
        prior = prior_sigmas(free, units, opts.prior_length, opts.prior_angle)
    fun = residual_function(model, free, ctx, m.p, W, prior)
    n_obs = 3 * m.n

    def jacobian(x: Tensor) -> Tensor:
        xg, xn = x[:n_geo], x[n_geo:]
        Jg = torch.func.jacfwd(lambda a: fun(torch.cat([a, xn])))(xg)  # observations and the geometry's prior
        with torch.no_grad():
            R = robot.T_tracker_base()[:3, :3]
            Jn = (W @ R @ net.jacobian_flat(xn, m.q)[1]).reshape(n_obs, -1)
        J = torch.zeros(len(Jg), len(x), dtype=x.dtype, device=x.device)
        J[:, :n_geo] = Jg
        J[:n_obs, n_geo:] = Jn  # the prior rows concern the geometry only
        return J

    return fun, jacobian


def _joint_restarts(fun, jacobian, free: FreeParameters, iterations: int, score, judged: bool) -> tuple[LMResult, dict]:
    """LM restarted with a fresh damping every JOINT_RESTART iterations (module constant); after each restart
    ``score(history)`` judges the state (lower is better), and the best one (the start included) is kept."""
    done, history, trail = 0, [], []
    best = (score(history), 0, free.vector())
    while done < iterations:
        res = levenberg_marquardt(
            fun, free.vector(), names=free.names, max_iter=min(JOINT_RESTART, iterations - done), jacobian=jacobian
        )
        if not bool(torch.isfinite(res.x).all()):
            raise EstimationError("integrated ANN-EKF: the joint refinement diverged")
        free.assign(res.x)
        done += max(res.iterations, 1)
        history += res.cost_history if not history else res.cost_history[1:]
        v = score(history)
        trail.append({"iterations": done, "validation_rmse_mm": v * 1e3 if judged else None})
        if v < best[0]:
            best = (v, done, free.vector())
        if res.iterations == 0 or len(res.cost_history) < 2:
            break
    free.assign(best[2])
    res.iterations, res.cost_history = done, history
    return res, {"iterations_run": done, "kept_after_iterations": best[1], "trail": trail}


def _errors(model: MeasurementModel, m: Measurements) -> Tensor:
    return errors(model, m, trajectory=True)


_rmse = S.rmse


def integrate_adaptive(
    run: CalibrationRun,
    train: Measurements,
    hold: Measurements,
    setting: Setting | None = None,
) -> IntegratedFilter:
    """The ``integrated`` method with the adaptive filter: geometry in the state (the paper's future work).

    The kinematic calibration of the ``geometric`` stage stays the reference the report compares with; the
    filter starts again from the nominal geometry with the tracker pose and lever arm of a rigid fit, as
    :class:`~torchcal.filter.adaptive.AdaptiveEKF` is designed and tested for, and estimates the identifiable
    geometric corrections and the output layer of a fixed random-feature network (``hidden`` tanh units) together
    along the training samples; the held-out last samples are its test phase. The final model is the filter's
    geometry (instrument translation back-substituted) plus a :class:`LearnedEffect` with its network, so
    ``predict`` reloads it like any run.

    ``setting`` (default ``Setting("adaptive")``): its ``hidden`` and ``gain`` set the random features (more and
    sharper features fit more, fewer and smoother ones extrapolate more gently), ``sigma_field`` the prior of the
    output layer (the field's expected RMS): the regularisation settings :func:`integrate_selected` chooses among
    on validation samples.
    ``scripts/integrated_trajectory.py`` measures the engines on simulated trajectories (README, "integrated").
    Steps: :func:`_adaptive_pass` (the filter), :func:`_install_adaptive` (the final model),
    :func:`_record_adaptive` (the report's record).
    """
    with torch.no_grad():  # the kinematic calibration's prediction: the report's reference G
        kinematic = run.model(Context(q=torch.cat([train.q, hold.q])))
    s = setting or Setting("adaptive")
    start, net, res, cfg = _adaptive_pass(run, train, hold, s.hidden, s.gain, s.sigma_field)
    _install_adaptive(run, start, net, res)
    after = run.add_stage(StageName.INTEGRATED)
    nw = len(res.active)  # the state is [w[active]; t; (d); gamma]
    filt = IntegratedFilter(
        _as_ekf_result(res), torch.cat([train.p, hold.p]), kinematic, train.n, cfg, res.w, res.P[:nw, :nw], res.active
    )
    _record_adaptive(
        run, filt, res, net, hold, after, {"hidden": s.hidden, "feature_gain": s.gain, "sigma_field_m": s.sigma_field}
    )
    return filt


def _adaptive_pass(
    run: CalibrationRun, train: Measurements, hold: Measurements, hidden: int, gain: float, sigma_field: float
):
    """The adaptive filter over the training samples from the nominal geometry with a rigid fit's tracker pose and
    lever arm, then its test phase on ``hold``; returns the start robot, the network, the result, the config."""
    from torchcal.filter.adaptive import AdaptiveConfig, AdaptiveEKF, random_features

    opts, robot = run.options, run.model.robot
    start = _nominal_copy(robot)
    place_instrument_and_tool(start, train.q, train.p)
    cfg = AdaptiveConfig(
        sigma_tracker=opts.sigma_tracker, sigma_joint=opts.sigma_joint, rank_tol=opts.rank_tol, sigma_field=sigma_field
    )
    net = random_features(dof=robot.dof, hidden=hidden, gain=gain, seed=int(opts.seed) + 1)
    flt = AdaptiveEKF(start, net, cfg)
    _console.info(
        f"integrated ANN-EKF (adaptive): geometry and a {robot.dof}-{hidden}-3 random-feature network "
        f"estimated together along {train.n} samples, then {hold.n} held-out ones predicted"
    )
    flt.parameters = flt.identify(train.q)
    y_in = torch.cat([train.p, torch.full_like(hold.p, float("nan"))])  # the held-out positions never reach it
    res = flt.run(torch.cat([train.q, hold.q]), y_in, train.n)
    if res.diverged:
        raise EstimationError(f"integrated ANN-EKF (adaptive): the filter {res.status}")
    return start, net, res, cfg


def _install_adaptive(run: CalibrationRun, start, net: CorrectionNet, res) -> None:
    """The final model: the filter's geometry (instrument translation back-substituted) and its network."""
    with torch.no_grad():
        run.model.robot.load_state_dict(res.apply(start).state_dict())
        net.set_flat(res.w)
    run.model.add(LearnedEffect(net))


def _as_ekf_result(res) -> EKFResult:
    """The adaptive result as an :class:`EKFResult` with a draw dimension of one (what the report's plots read)."""
    return EKFResult(
        geometric=res.geometric[None],
        nongeometric=res.nongeometric[None],
        nis=res.nis[None],
        q_yy=res.q_yy[None],
        w=res.w[None],
        t=res.t[None],
        P=res.P[None],
        n_train=res.n_train,
        status=[res.status],
        seconds=res.seconds,
    )


def _record_adaptive(
    run: CalibrationRun, filt: IntegratedFilter, res, net: CorrectionNet, hold: Measurements, after, settings: dict
) -> None:
    """The adaptive engine's effect record (settings, the geometry with its sigmas, the filter's health) and note."""
    n_train = filt.n_train
    e_filter = (filt.prediction[n_train:] - hold.p).norm(dim=-1)
    nis = res.nis[:n_train]
    run.effects.append(
        _integrated_record(
            run,
            after,
            params={
                "model": "network (fixed random tanh features, output layer estimated)",
                **settings,
                "n_weights": net.n_weights,
                "fit": "adaptive ANN-EKF: identifiable geometry, lever arm, instrument rotation and the network "
                "in one filter state (Horvath & Neuner 2024, Sec. 4 future work)",
            },
            evidence={
                "holdout_rmse_filter_prediction_mm": _rmse(e_filter) * 1e3,
                "geometry": {
                    name: {"value": float(v), "std": float(s)}
                    for name, v, s in zip(res.names, res.gamma, res.gamma_std)
                },
                "filter": {
                    "engine": "adaptive",
                    "status": res.status,
                    "samples_filtered": n_train,
                    "seconds": res.seconds,
                    "nis_mean": float(nis.nanmean()),
                    "nis_expected": 3.0,
                    "linearisation_remainder_m": [r.get("total_remainder_m") for r in res.relinearisations],
                },
            },
        )
    )
    run.notes.append(
        f"integrated ANN-EKF (adaptive): held-out RMSE {after.rmse * 1e3:.4f} mm (final model), the "
        f"filter's own test-phase prediction {_rmse(e_filter) * 1e3:.4f} mm; mean NIS "
        f"{float(nis.nanmean()):.2f} (3 expected)"
    )


def _nominal_copy(robot):
    """A copy of ``robot`` with every correction at zero (its nominal geometry, instrument and lever arm)."""
    out = copy.deepcopy(robot)
    with torch.no_grad():
        for g in out.groups().values():
            g.delta.zero_()
    return out


#: the last VALIDATION_FRACTION of the training samples choose the integrated model: a block at the end, in time
#: order, so that the choice is judged on how a model predicts the *continuation* of the path it was fitted on,
#: which is what the held-out samples (and a user's next program) ask of it
VALIDATION_FRACTION = 0.2
#: the validation block is cut into this many consecutive pieces, and a candidate must beat geometry alone on the
#: block with any one piece left out: one block of a path is a single draw of how a model extrapolates, and a
#: filter that wins it on average by one good stretch can lose on the path's continuation. (Winning *every* piece,
#: the rule before, also rejected filters that lose one stretch narrowly and win the rest clearly -- on the outside
#: trajectory the one that halves geometry's error on the continuation.)
VALIDATION_PIECES = 4


def leave_one_piece_out(e: Tensor, e_ref: Tensor, pieces: int = VALIDATION_PIECES) -> tuple[list, list]:
    """RMSE ratios of ``e`` to ``e_ref`` per consecutive piece, and over the block with each piece left out.

    Args:
        e, e_ref: per-sample errors ``(N,)`` [m] of a candidate and of the reference on the same samples.

    Returns:
        ``(per_piece, left_out)``, ``pieces`` ratios each; a candidate is kept only if every ``left_out`` is < 1.
    """
    a, b = e.tensor_split(pieces), e_ref.tensor_split(pieces)
    per_piece = [_rmse(x) / _rmse(y) for x, y in zip(a, b)]
    left_out = [_rmse(torch.cat(a[:j] + a[j + 1 :])) / _rmse(torch.cat(b[:j] + b[j + 1 :])) for j in range(pieces)]
    return per_piece, left_out


#: the longest support gate the paper's engine is tried behind (in units of the joints' training spread)
EKF_LONGEST_GATE = 0.5


@dataclass(frozen=True)
class Setting:
    """One candidate of the integrated method: an engine and its capacity / regularisation."""

    engine: str  # "adaptive" or "ekf"
    hidden: int = 128
    gain: float = 5.0  # random features' Glorot gain (adaptive)
    sigma_field: float = 5e-4  # prior RMS of the network's correction [m] (adaptive)

    @property
    def gate_lengths(self) -> tuple[float, ...]:
        """Support-gate lengths tried on validation. The paper's engine is kept only behind a finite gate: its
        6-29-3 network, refined jointly with a geometry of its own, can beat geometry alone on every piece of the
        validation block and still extrapolate worse than geometry on the path's continuation (README,
        *The integrated method on paths it was not tuned on*); a gate bounds how far that can go."""
        return tuple(g for g in sup.GATE_LENGTHS if g <= EKF_LONGEST_GATE) if self.engine == "ekf" else sup.GATE_LENGTHS

    @property
    def name(self) -> str:
        if self.engine == "ekf":
            return f"ekf (paper's filter, 6-{self.hidden}-3 network)"
        return f"adaptive ({self.hidden} features, gain {self.gain:g}, prior {self.sigma_field * 1e3:g} mm)"


#: the candidates :func:`integrate_selected` tries besides geometry alone: the adaptive engine as designed, with a
#: tighter prior, with smoother features, with fewer smoother features, and the paper's engine
SETTINGS = (
    Setting("adaptive"),
    Setting("adaptive", sigma_field=1e-4),
    Setting("adaptive", gain=2.0),
    Setting("adaptive", hidden=32, gain=2.0),
    Setting("ekf", hidden=29),
)


def _run_setting(run: CalibrationRun, train: Measurements, hold: Measurements, setting: Setting) -> IntegratedFilter:
    if setting.engine == "ekf":
        return integrate(run, train, hold)
    return integrate_adaptive(run, train, hold, setting)


def _scratch(run: CalibrationRun, model: MeasurementModel, train_idx: Tensor, holdout_idx: Tensor) -> CalibrationRun:
    """A throw-away copy of ``run`` for one candidate: its own model, ``train_idx`` its training set and
    ``holdout_idx`` its held-out set (rows of ``run.data``), its own records."""
    trial = copy.copy(run)
    trial.model = copy.deepcopy(model)
    trial.robot = trial.model.robot
    trial.train_idx, trial.holdout_idx = train_idx, holdout_idx
    trial.fits, trial.effects, trial.rejections, trial.notes, trial.stages = list(run.fits), [], [], [], []
    trial.add_stage(StageName.GEOMETRIC)
    return trial


def _gated(model: MeasurementModel, support: Tensor, length: float, fallback) -> MeasurementModel:
    """``model`` with its last (learned) effect behind a support gate falling back to ``fallback``."""
    # a new model around the same robot and effects (copy.copy of a Module would share its submodule table, and
    # replacing the effect there would wrap the original model's effect too)
    return MeasurementModel(
        model.robot, [*model.effects[:-1], sup.SupportGate(model.effects[-1], support, length, fallback=fallback)]
    )


def integrate_selected(
    run: CalibrationRun, train: Measurements, hold: Measurements, *, settings: tuple[Setting, ...] = SETTINGS
) -> IntegratedFilter | None:
    """The ``integrated`` method that keeps only what validation supports: never worse than geometry by design.

    The training samples are split in time: the first ``1 - VALIDATION_FRACTION`` fit, the last block validates.
    Geometry alone (the kinematic calibration refitted on the fitting samples) and every ``settings`` candidate
    (an engine with its capacity and prior, fitted on the fitting samples, the validation block its test phase)
    predict the validation block. Each is also tried behind a :class:`~torchcal.effects.support.SupportGate` of
    the lengths in :data:`~torchcal.effects.support.GATE_LENGTHS` (no gate among them), which fades the
    prediction back to the kinematic calibration where the path leaves the joints the filter was trained on. The
    candidate with the lowest validation RMSE is kept only if it beats geometry alone by a one-sided paired test
    at ``run.options.alpha_validation``, with the standard error inflated for the autocorrelation of
    neighbouring samples (:func:`torchcal.stats.paired_test`); it is then fitted again on all training samples
    (the held-out samples its test phase) with the gate length chosen. Otherwise the run ends with the geometric
    model and says why. A candidate must also beat geometry alone on the validation block with any one of its
    :data:`VALIDATION_PIECES` pieces left out (:func:`leave_one_piece_out`). The table of candidates goes into the
    report (the effect's or the rejection's ``evidence["selection"]``). The kept model predicts a standard
    deviation per sample, calibrated on the validation block (:func:`_attach_predictive_sigma`,
    ``evidence["predictive_sigma"]``; ``predict`` writes it as ``sx, sy, sz``).
    """
    opts = run.options
    n_val = max(1, int(round(VALIDATION_FRACTION * train.n)))
    n_fit = train.n - n_val
    fit, val = train.subset(slice(0, n_fit)), train.subset(slice(n_fit, None))
    ida = next((f.identifiability for f in reversed(run.fits) if f.identifiability is not None), None)
    geo = copy.deepcopy(run.model)
    solve(geo, fit, GEOMETRIC_GROUPS, opts, "integrated: geometry on the fitting samples", True, identifiability=ida)
    e_geo = _errors(geo, val)
    table = [{"candidate": "geometry alone", "validation_rmse_mm": _rmse(e_geo) * 1e3}]
    best = None
    for setting in settings:
        _console.info(f"integrated: validating {setting.name} on the last {val.n} training samples")
        trial = _scratch(run, geo, run.train_idx[:n_fit], run.train_idx[n_fit:])
        try:
            trial_filter = _run_setting(trial, fit, val, setting)
        except EstimationError as err:
            table.append({"candidate": setting.name, "failed": str(err)})
            continue
        length, gates = sup.choose_gate_length(
            lambda ell, m=trial.model: _gated(m, fit.q, ell, geo.robot),
            lambda m: _rmse(_errors(m, val)),
            setting.gate_lengths,
        )
        e = _errors(_gated(trial.model, fit.q, length, geo.robot), val)
        pieces, left_out = leave_one_piece_out(e, e_geo)
        row = {
            "candidate": setting.name,
            "validation_rmse_mm": _rmse(e) * 1e3,
            "gate_length": length,
            "piece_ratios_to_geometry": pieces,
            "leave_one_piece_out_ratios": left_out,
            "gates": [{"length": g["length"], "validation_rmse_mm": g["validation_rmse_m"] * 1e3} for g in gates],
        }
        table.append(row)
        if max(left_out) < 1.0 and (best is None or _rmse(e) < _rmse(best[2])):
            best = (setting, length, e, row, trial.model, trial_filter)
    evidence = {
        "rule": f"lowest validation RMSE among the candidates better than geometry alone on the validation block "
        f"with any one of its {VALIDATION_PIECES} consecutive pieces left out, kept when it beats geometry alone by "
        f"a one-sided paired test (autocorrelation-corrected) at p < {opts.alpha_validation}",
        "n_fit": fit.n,
        "n_validation": val.n,
        "candidates": table,
    }
    accepted = False
    if best is not None:
        test = S.paired_test(e_geo, best[2], ordered=True)
        evidence.update(chosen=best[3]["candidate"], test={k: test[k] for k in ("z", "p_value", "n")})
        accepted = _rmse(best[2]) < _rmse(e_geo) and test["p_value"] < opts.alpha_validation
    if not accepted:
        why = (
            "no candidate beats geometry alone on the validation block with any one of its pieces left out"
            if best is None
            else f"the best candidate, {best[3]['candidate']}, does not beat geometry alone on the validation block "
            f"({_rmse(e_geo) * 1e3:.4f} -> {best[3]['validation_rmse_mm']:.4f} mm, p = "
            f"{evidence['test']['p_value']:.2g})"
        )
        run.rejections.append(Rejection("learned", None, {"selection": evidence}, name="integrated", reason=why))
        run.notes.append(f"integrated: geometry alone kept: {why}")
        if opts.refits:
            evidence["refit"] = refit_geometry(run, ida)
        return None
    setting, length = best[0], best[1]
    _console.info(f"integrated: {setting.name} chosen on validation; fitted again on all {train.n} training samples")
    # the kinematic calibration on all training samples, kept apart: the engines edit run.model's robot in place
    geometric = copy.deepcopy(run.model)
    kinematic = geometric.robot
    n_effects, n_stages = len(run.effects), len(run.stages)
    filt = _run_setting(run, train, hold, setting)
    record = run.effects[-1]
    length = _gate_on_holdout(run.model, train, hold, kinematic, setting, length, evidence)
    sigma = _attach_predictive_sigma(run, filt, kinematic, geo, best[4], best[5], fit, val, train, hold, length)
    record.params["support_gate_length"] = length
    record.evidence["selection"] = evidence
    record.evidence["predictive_sigma"] = sigma
    guard = _holdout_guard(run.model, geometric, hold)
    evidence["holdout_guard"] = guard
    if guard["passed"]:
        if opts.refits:
            record.evidence["refit"] = _refit_filter(run, setting, length, geometric, ida)
        return filt
    # the refit on all training samples is worse than geometry alone where neither was fitted: geometry it is (the
    # run's robot too, which the adaptive engine changed in place and the report exports)
    run.model, run.robot = geometric, geometric.robot
    del run.effects[n_effects:], run.stages[n_stages:]
    why = (
        f"{setting.name}, chosen on validation, is worse than geometry alone on the held-out samples once fitted "
        f"again on all training samples ({guard['geometry_rmse_mm']:.4f} -> {guard['rmse_mm']:.4f} mm)"
    )
    run.rejections.append(Rejection("learned", None, {"selection": evidence}, name="integrated", reason=why))
    run.notes.append(f"integrated: geometry alone kept: {why}")
    if opts.refits:
        evidence["refit"] = refit_geometry(run, ida)
    return None


def refit_geometry(run: CalibrationRun, identifiability) -> dict:
    """Fit the run's geometry (``run.model``, the kinematic calibration) again on all samples, training and
    held-out (``Options.refit``), from its fit on the training samples. The fit joins ``run.fits`` (the report's
    parameters and global test are then the refit's); the stages keep the held-out errors of the fit that did not
    see them. Returns the report's evidence."""
    both = run.fitted_and_held_out
    _console.info(f"geometry fitted again on all {both.n} samples (the held-out errors stay the training fit's)")
    fit = _geometry_on_all(run, run.model, identifiability, "refit: geometry on all samples")
    run.fits.append(fit)
    run.notes.append(
        f"refit: the model written was fitted again on all {both.n} samples (training and held-out); the held-out "
        f"errors reported are those of the same fit on the {len(run.train_idx)} training samples only"
    )
    return {"n_samples": both.n, "model": "geometry", "status": fit.result.status}


def _geometry_on_all(run: CalibrationRun, model: MeasurementModel, identifiability, stage: str):
    """``model``'s geometry fitted (in place) on all of ``run``'s samples, training and held-out; returns the fit."""
    return solve(
        model,
        run.fitted_and_held_out,
        GEOMETRIC_GROUPS,
        run.options,
        stage,
        run.trajectory,
        identifiability=identifiability,
    )


def _refit_filter(run: CalibrationRun, setting: Setting, length: float, geometric: MeasurementModel, ida) -> dict:
    """The chosen filter fitted again on all samples, training and held-out (``Options.refit``), as the model
    ``run.model`` writes: the engine of ``setting`` on all of them (the paper's engine judges its joint refinement
    on its own last samples, as on the training samples), behind a gate of the chosen ``length`` around all of
    them that falls back to the geometry fitted again on all of them, with the predictive sigma's calibration of
    the fit on the training samples (scale, floor, fallback scale and growth) and the refit's own weight
    covariance. On a trajectory the held-out last samples are the nearest to the path's continuation; selection,
    held-out guard and the reported held-out errors are those of the fit on the training samples. A refit that
    fails (a diverging pass) keeps the training fit, and the note says so. Returns the report's evidence."""
    both = run.fitted_and_held_out
    _console.info(f"integrated: {setting.name} fitted again on all {both.n} samples, training and held-out")
    geo_all = copy.deepcopy(geometric)
    fit = _geometry_on_all(run, geo_all, ida, "integrated: geometry on all samples (refit)")
    trial = _scratch(run, geometric, torch.cat([run.train_idx, run.holdout_idx]), run.holdout_idx[:0])
    try:
        filt = _run_setting(trial, both, both.subset(slice(both.n, None)), setting)
    except EstimationError as err:
        why = f"the refit on all {both.n} samples failed ({err}); the model written is the training fit"
        run.notes.append(f"refit: {why}")
        return {"n_samples": both.n, "skipped": why}
    old = run.model.effects[-1]  # the training fit's gate, with the predictive sigma's calibration
    gate = _predictive_gate(
        trial.model,
        filt,
        both.q,
        length,
        geo_all.robot,
        old.sigma_noise,
        old.sigma_far,
        old.sigma_length,
        old.sigma_scale,
        old.sigma_floor,
    )
    gate.sigma_fallback, gate.fallback_growth = old.sigma_fallback, old.fallback_growth
    trial.model.effects[-1] = gate
    run.model, run.robot = trial.model, trial.model.robot
    run.notes.append(
        f"refit: the model written is {setting.name} fitted again on all {both.n} samples (training and held-out), "
        f"behind the same gate around all of them; the held-out errors reported are those of the same choice "
        f"fitted on the {len(run.train_idx)} training samples only"
    )
    return {
        "n_samples": both.n,
        "model": setting.name,
        "gate_length": length,
        "filter_status": trial.effects[-1].evidence["filter"]["status"],
        "geometry_fallback_status": fit.result.status,
    }


def _gate_on_holdout(
    model: MeasurementModel,
    train: Measurements,
    hold: Measurements,
    kinematic,
    setting: Setting,
    length: float,
    evidence: dict,
) -> float:
    """The gate length the final model keeps: the shorter of the one chosen on the validation block (``length``,
    the candidate fitted on the fitting samples) and the one the held-out samples choose for the final model fitted
    on all training samples (``model``, its learned effect not yet gated; the gate around the training samples,
    falling back to the kinematic calibration). Each block is one stretch of the path leaving the samples fitted,
    and a gate is kept only as long as both support: where the validation block favoured a long gate and the
    held-out samples a shorter one, the longer one extrapolated worse on the continuation (README, *The integrated
    method on paths it was not tuned on*). Only shortens: the held-out samples never lengthen the gate, so the held-out
    guard that follows judges a model at most as far from geometry as validation chose. The table goes into
    ``evidence["gate_on_holdout"]``; with fewer held-out samples than validation pieces, ``length`` is kept."""
    if hold.n < VALIDATION_PIECES:
        return length
    chosen, gates = sup.choose_gate_length(
        lambda ell: _gated(model, train.q, ell, kinematic),
        lambda m: _rmse(_errors(m, hold)),
        setting.gate_lengths,
    )
    kept = min(length, chosen)
    evidence["gate_on_holdout"] = {
        "rule": "the shorter of the gate chosen on the validation block and the one the held-out samples choose "
        "for the final model",
        "validation_gate_length": length,
        "holdout_gate_length": chosen,
        "kept": kept,
        "gates": [{"length": g["length"], "holdout_rmse_mm": g["validation_rmse_m"] * 1e3} for g in gates],
    }
    return kept


def _holdout_guard(model: MeasurementModel, geometric: MeasurementModel, hold: Measurements) -> dict:
    """Whether the final ``model`` is better than the kinematic calibration ``geometric`` on the held-out samples
    (the continuation of the path, fitted by neither): a lower RMSE there with any one of its
    :data:`VALIDATION_PIECES` pieces left out, as on validation (no significance asked: validation chose, this only
    refuses a refit that made things worse). Passed when there are no held-out samples to judge on."""
    if hold.n < VALIDATION_PIECES:
        return {"passed": True, "n": hold.n, "rule": "too few held-out samples to judge"}
    e, e_geo = _errors(model, hold), _errors(geometric, hold)
    _, left_out = leave_one_piece_out(e, e_geo)
    return {
        "passed": bool(_rmse(e) < _rmse(e_geo) and max(left_out) < 1.0),
        "n": hold.n,
        "rmse_mm": _rmse(e) * 1e3,
        "geometry_rmse_mm": _rmse(e_geo) * 1e3,
        "leave_one_piece_out_ratios": left_out,
        "rule": "lower held-out RMSE than geometry alone with any one of the pieces left out",
    }


def _attach_predictive_sigma(
    run: CalibrationRun,
    filt: IntegratedFilter,
    kinematic,
    geo: MeasurementModel,
    val_model: MeasurementModel,
    val_filter: IntegratedFilter,
    fit: Measurements,
    val: Measurements,
    train: Measurements,
    hold: Measurements,
    length: float,
) -> dict:
    """Put the final model's learned effect behind its support gate with a predictive standard deviation.

    The scale factor is calibrated on the validation block with the candidate fitted on the fitting samples
    (``val_model``, ``val_filter``) behind the same gate falling back to geometry on the fitting samples (``geo``);
    the final gate falls back to the kinematic calibration on all training samples (``kinematic``). The fallback's
    error and its growth with distance come from geometry's own residuals (:func:`_fallback_growth`) before the
    scale is fitted. The network's error far from the support tends to its gate's fallback's residual scale
    ``s_far``: geometry on the fitting samples on the validation block for the candidate's gate, the kinematic
    calibration on the held-out samples for the final gate (without held-out samples, the former for both). The
    scale and floor are fitted by likelihood on the validation block, then widened (never
    narrowed) by the factor that puts :data:`COVERAGE_TARGET` of the validation and held-out residuals together
    within 2 sigma, each block with its own model: the candidate on validation, the final model on the held-out
    samples (:func:`~torchcal.effects.support.fit_predictive_scale`); without held-out samples, to the target on
    validation only. The held-out coverage is then part of the calibration, not an independent
    check: the test file (the path's continuation) is. Always a gate, an infinite one included (it changes no
    prediction): it carries the standard deviation. Returns the report's evidence (scale, coverage of 2 sigma on
    validation and on the held-out samples, the rule, the variance's parts).
    """
    noise = _observation_sigma(run.model, train, run.options)
    # each fallback's residuals beyond its own support: geometry on the fitting samples on the validation block,
    # the kinematic calibration (geometry on all training samples) on the held-out samples
    e_geo = _residuals(geo, val)
    e_kin = _residuals(MeasurementModel(kinematic, []), hold) if hold.n else None
    far = e_geo.square().mean(dim=0).sqrt()  # geometry's residual scale per axis on validation
    sigma_length = length if math.isfinite(length) else max(g for g in sup.GATE_LENGTHS if math.isfinite(g))
    val_gate = _predictive_gate(val_model, val_filter, fit.q, length, geo.robot, noise, far, sigma_length)
    fb_sigma, fb_growth = _fallback_growth(run, kinematic, e_geo, e_kin, val, train, hold, val_gate)
    val_gate.sigma_fallback, val_gate.fallback_growth = fb_sigma, fb_growth
    e_val = _residuals(val_model, val, val_gate)
    # each gate's far part is its own fallback's residual scale beyond that fallback's support: geometry's on the
    # validation block for the candidate; the kinematic calibration's on the held-out samples for the final model
    # (a geometry on all training samples, better determined than the one on fewer)
    far_final = far if e_kin is None else e_kin.square().mean(dim=0).sqrt()
    gate = _predictive_gate(run.model, filt, train.q, length, kinematic, noise, far_final, sigma_length)
    gate.sigma_fallback, gate.fallback_growth = fb_sigma, fb_growth
    holdout = None
    if hold.n:  # the final model's residuals and variance parts where it was not fitted (its own P_w, its gate)
        with torch.no_grad():
            holdout = (_residuals(run.model, hold, gate), *gate.variance_parts(run.model.robot, hold.q))
    scale, floor = sup.fit_predictive_scale(
        e_val, *val_gate.variance_parts(val_model.robot, val.q), COVERAGE_TARGET, holdout=holdout
    )
    val_gate.sigma_scale, val_gate.sigma_floor = scale, floor
    gate.sigma_scale, gate.sigma_floor = scale, floor
    run.model.effects[-1] = gate
    run.stages.pop()
    run.effects[-1].rmse_after_mm = run.add_stage(StageName.INTEGRATED).rmse * 1e3
    # each block's residuals (computed above; the scale changes no prediction) against its predicted sigma
    with torch.no_grad():
        blocks = [(e_val, val_gate.predictive_std(val_model.robot, val.q))]
        if hold.n:
            blocks.append((holdout[0], gate.predictive_std(run.model.robot, hold.q)))
    cov_val = sup.coverage(*blocks[0])
    cov_hold = sup.coverage(*blocks[1]) if hold.n else None
    check = _sigma_check(blocks)
    if check["suspect"]:
        run.notes.append(
            f"integrated: the predictive sigma reaches {check['max_sigma_mm']} mm, {check['ratio']} times the "
            "largest validation or held-out residual: the widening factor was set by samples where the network's "
            "part of the variance is nearly zero; treat the sx, sy, sz columns of predict as unreliable"
        )
    return {
        "scale": scale,
        "floor_mm": [f * 1e3 for f in floor],
        "target_coverage_2sigma": COVERAGE_TARGET,
        "calibration": "likelihood on validation, then widened (never narrowed) to the target over validation and "
        "held-out residuals together (held-out coverage calibrated, not independent)"
        if hold.n
        else "likelihood on validation, then widened (never narrowed) to the target on validation",
        "coverage_2sigma_validation": cov_val,
        "coverage_2sigma_holdout": cov_hold,
        "n_validation": val.n,
        "n_holdout": hold.n,
        "sigma_noise_mm": (noise * 1e3).tolist(),
        "sigma_far_mm": (far * 1e3).tolist(),
        "sigma_far_final_mm": (far_final * 1e3).tolist(),
        "sigma_length": sigma_length,
        "fallback_sigma_mm": [x * 1e3 for x in fb_sigma],
        "fallback_growth": fb_growth,
        "sigma_check": check,
    }


def _fallback_growth(
    run: CalibrationRun,
    kinematic,
    e_geo: Tensor,
    e_kin: Tensor | None,
    val: Measurements,
    train: Measurements,
    hold: Measurements,
    val_gate: sup.SupportGate,
) -> tuple[list[float], float]:
    """How the geometric model's error grows with the distance from the samples it was fitted on
    (:func:`~torchcal.effects.support.fit_fallback_growth`): its residuals on the validation block (geometry on the
    fitting samples, ``e_geo``) and on the second half of the training samples (geometry refitted on the first half,
    from the kinematic calibration), each at its distance from the samples fitted. The validation block alone
    reaches only a short way from the support; a path's continuation can leave it much further (a random walk),
    and the second half of the training samples shows how far geometry's residual grows over a longer stretch.
    Those refits only give the growth's shape where there are held-out samples: the scale then comes from the
    kinematic calibration itself, the fallback the prediction uses, on the held-out samples at their distance from
    all training samples, ``e_kin`` (:func:`~torchcal.effects.support.fit_fallback_scale`; None without them).
    Geometry fitted on all training samples is better determined than one fitted on half of them: scaled by the
    refits, the fallback part overstated its error on the continuation where the path leaves the training joints
    (README, *Predictive standard deviation*)."""
    half = train.n // 2
    first, second = train.subset(slice(0, half)), train.subset(slice(half, None))
    ida = next((f.identifiability for f in reversed(run.fits) if f.identifiability is not None), None)
    geo_half = MeasurementModel(copy.deepcopy(kinematic), [])
    stage = "integrated: geometry on the first half (sigma)"
    solve(geo_half, first, GEOMETRIC_GROUPS, run.options, stage, True, identifiability=ida)
    half_gate = sup.SupportGate(val_gate.inner, first.q, math.inf)  # only its distance to the first half is used
    e = torch.cat([e_geo, _residuals(geo_half, second)])
    d = torch.cat([val_gate.distance(val.q), half_gate.distance(second.q)])
    s_fb, growth = sup.fit_fallback_growth(e, d)
    if e_kin is None:
        return s_fb, growth
    all_gate = sup.SupportGate(val_gate.inner, train.q, math.inf)  # the final gate's support: all training samples
    return sup.fit_fallback_scale(e_kin, all_gate.distance(hold.q), growth), growth


#: the share of residual components within two predicted standard deviations the scale factor is calibrated to
COVERAGE_TARGET = 0.95


def _observation_sigma(model: MeasurementModel, m: Measurements, opts) -> Tensor:
    """Measurement noise per tracker axis ``(3,)`` [m]: the tracker's (median of the per-point sigmas where the
    data have them) and the joint noise at the probe, ``sigma_joint |J_q|_F / sqrt(3)`` (median over the samples)."""
    tracker = float(m.sigma.median()) if m.sigma is not None else opts.sigma_tracker
    with torch.no_grad():
        _, Jq = model.robot.probe_jacobian(m.q)
    joint = opts.sigma_joint * float(Jq.flatten(-2).norm(dim=-1).median()) / math.sqrt(3.0)
    return torch.full((3,), math.hypot(tracker, joint), dtype=m.q.dtype, device=m.q.device)


def _residuals(model: MeasurementModel, m: Measurements, gate: sup.SupportGate | None = None) -> Tensor:
    """Prediction minus measurement per tracker axis ``(N, 3)`` [m]; with ``gate`` replacing the last effect."""
    if gate is not None:
        model = MeasurementModel(model.robot, [*model.effects[:-1], gate])
    with torch.no_grad():
        return model(Context.from_measurements(m, trajectory=True)) - m.p


def _predictive_gate(
    model: MeasurementModel,
    filt: IntegratedFilter,
    support: Tensor,
    length: float,
    fallback,
    noise: Tensor,
    far: Tensor,
    sigma_length: float,
    scale: float = 1.0,
    floor=None,
) -> sup.SupportGate:
    """``model``'s last (learned) effect behind a support gate that also predicts its standard deviation."""
    inner = model.effects[-1]
    inner = inner.inner if isinstance(inner, sup.SupportGate) else inner
    gate = sup.SupportGate(inner, support, length, fallback=fallback)
    gate.set_predictive(filt.weight_cov, filt.weight_index, noise, far, sigma_length, scale, floor)
    return gate


#: a predictive sigma this many times the largest residual of the blocks it was calibrated on is numerical trouble:
#: half the cap of the widening factor (support.FACTOR_SIGMA_RATIO), so that a capped factor is always reported
SIGMA_CHECK_RATIO = 0.5 * sup.FACTOR_SIGMA_RATIO


def _sigma_check(blocks: list[tuple[Tensor, Tensor]]) -> dict:
    """The largest predicted standard deviation of ``(residuals, sigma)`` blocks (the validation and held-out ones,
    ``(N, 3)`` [m] each) against their largest residual: ``suspect`` when it is not finite or more than
    :data:`SIGMA_CHECK_RATIO` times that residual. The widening factor
    (:func:`~torchcal.effects.support.calibrate_factor`) is a quantile of what each residual component needs from the
    near part of the variance; where that part is nearly zero (a gate almost closed) the need, and with it every
    other sample's sigma, grows until the factor's cap. Reported, not hidden."""
    sd = torch.cat([b[1].flatten() for b in blocks])
    e = torch.cat([b[0].abs().flatten() for b in blocks])
    top, worst = float(sd.max()), float(e.max().clamp_min(1e-12))
    ratio = top / worst
    return {
        "max_sigma_mm": top * 1e3 if math.isfinite(top) else None,
        "max_residual_mm": worst * 1e3,
        "ratio": ratio if math.isfinite(ratio) else None,
        "suspect": not math.isfinite(ratio) or ratio > SIGMA_CHECK_RATIO,
    }
