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
   to what is left extrapolates worse than one fitted with the true geometry (``scripts/integrated_trajectory.py``
   compares the two); estimating both together can move
   that share back, but it can also make things worse, so the last 10 % of the training samples judge it
   after every restart and the best state (possibly the unrefined start) is kept;
4. the EKF pass over the training samples (:class:`~torchcal.filter.EKFTrainer`) from the refined weights,
   the probe position pinned to the refined kinematics (the geometry is estimated already, and the filter
   cannot estimate it -- the paper leaves that "adaptive" step to future work, and so do we), the weights a
   slow random walk (stochastic model: the constants below);
5. the test phase: the held-out last 20 % of the trajectory, predicted without updates.

The paper's ANN re-iteration (Fig. 10: an LM re-fit every 500 samples to the corrections of Eq. 22, taken
against the filter's own geometric state, without a validation share) is off by default
(``reiterate_every=0``; the argument switches it on): without a validation share nothing keeps such a re-fit from
fitting the filter's own corrections of the training stretch at the expense of the path's continuation
(docs/integrated.md, *The engines*), and each pass costs an LM fit every 500 samples.

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

import torch

from torchcal import _console
from torchcal import stats as S
from torchcal._method import Engine
from torchcal.data import Measurements
from torchcal.effects import Context, CorrectionNet, LearnedEffect, MeasurementModel
from torchcal.effects import predictive as P
from torchcal.effects import region as gating
from torchcal.errors import EstimationError, OptionError
from torchcal.estimate.fit import GEOMETRIC_GROUPS, errors, place_instrument_and_tool, solve
from torchcal.estimate.joint_refinement import refine_jointly
from torchcal.filter.ekf import EKFConfig, EKFResult, EKFTrainer
from torchcal.pipeline.holdout import (
    GUARD_MIN_POSES,
    VALIDATION_PIECES,
    geometry_on_all,
    guard_against_geometry,
    leave_one_piece_out,
    refit_geometry,
)
from torchcal.pipeline.records import Cause, EffectRecord, IntegratedFilter, Rejection, StageName
from torchcal.pipeline.state import CalibrationRun, StageResult, StageWork

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
#: LM iterations of the joint refinement of geometry and network (step 3;
#: :func:`torchcal.estimate.joint_refinement.refine_jointly`)
JOINT_ITERATIONS = 150
#: the joint refinement uses every JOINT_STRIDE-th training sample: neighbouring samples of a trajectory carry
#: nearly the same information, and the thinned set keeps an iteration cheap
JOINT_STRIDE = 3
#: the last FORWARD_FRACTION of the training samples judge the joint refinement, after each restart, against
#: not refining at all (neither the network's initial fit nor the refinement sees them; the geometry refit and
#: the filter do): the held-out samples continue the trajectory, so the state that predicts the *next* stretch
#: best is kept, not the one that interpolates a random share best
FORWARD_FRACTION = 0.1


def require_trajectory(data: Measurements, trajectory: bool) -> None:
    """Raise :class:`OptionError` unless ``data`` is a continuous trajectory with a monotonic ``t`` column."""
    where = f"{data.source}: " if data.source else ""
    other = "use method kinematic, kinematic+ann or auto for static poses (--method)"
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
    """The filter's configuration for an integrated work (module constants and the work's stochastic model).

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
    work: StageWork,
    train: Measurements,
    hold: Measurements,
    *,
    joint_iterations: int = JOINT_ITERATIONS,
    reiterate_every: int = 0,
    pcm_iterations: int | None = None,
) -> IntegratedFilter:
    """Steps 2-5 of the module docstring on a work whose geometric stage is done; adds the ``integrated`` stage.

    Args:
        work: the :class:`~torchcal.pipeline.state.StageWork` (its model holds the calibrated geometry and no
            effects yet).
        train, hold: the training samples and the held-out last samples of the trajectory, in time order.
        joint_iterations: LM iterations of the joint refinement (0: none).
        reiterate_every: the paper's ANN re-iteration period in samples (0, the default: none; module docstring).
        pcm_iterations: LM iterations of the network's initial fit (default ``work.options.network.iterations``).
    """
    model, robot, opts = work.model, work.model.robot, work.options
    cfg = filter_config(model, train, opts.fit.sigma_tracker, opts.fit.sigma_joint, reiterate_every)
    net = CorrectionNet(robot.dof, opts.network.hidden, device=robot.device)
    net.reset_parameters(torch.Generator().manual_seed(int(opts.seed) + S.Stream.NETWORK_INIT), gain=0.5)
    trainer = EKFTrainer(robot, net, cfg)
    steps = {}
    _console.info(
        f"integrated ANN-EKF: network {robot.dof}-{opts.network.hidden}-3 initialised by LM on the training corrections"
    )
    n_fit = train.n - max(1, int(round(FORWARD_FRACTION * train.n)))
    fit, forward = train.subset(slice(0, n_fit)), train.subset(slice(n_fit, None))
    net.set_flat(
        trainer.pcm_weights(
            fit.q, fit.p, net.flat(), iterations=pcm_iterations or opts.network.iterations, seed=int(opts.seed)
        )
    )
    model.add(LearnedEffect(net))
    steps["initial_network"] = _rmse(_errors(model, hold))
    ida = work.identifiability
    joint_info = None
    if joint_iterations > 0:
        _console.info(
            f"integrated ANN-EKF: geometry, instrument, lever arm and network refined jointly "
            f"(up to {joint_iterations} LM iterations, judged on the last {forward.n} training samples)"
        )
        joint, joint_info = refine_jointly(
            model, fit.subset(slice(None, None, JOINT_STRIDE)), ida, opts.fit, joint_iterations, validation=forward
        )
        joint_info["status"] = joint.status
        steps["joint_refinement"] = _rmse(_errors(model, hold))
    # the geometry's final least-squares fit with the network in place: its statistics go into the report
    work.fits.append(
        solve(
            model,
            train,
            GEOMETRIC_GROUPS,
            opts.fit,
            "integrated (geometry with the network in place)",
            trajectory=True,
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
    work.add_stage(StageName.INTEGRATED)
    _record_ekf(work, filt, steps, joint_info, hold, net.n_weights)
    return filt


def _integrated_record(work: StageWork, after, *, params: dict, evidence: dict) -> EffectRecord:
    """The integrated work's effect record (the learned correction, stage ``learned``), with the held-out RMSE of
    the geometric stage before it and of the stage ``after`` it."""
    before = work.stage(StageName.GEOMETRIC)
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
    work: StageWork,
    filt: IntegratedFilter,
    steps: dict,
    joint_info: dict | None,
    hold: Measurements,
    n_weights: int,
) -> None:
    """The ``ekf`` engine's effect record and note: held-out RMSE after each step, the filter's statistics."""
    opts, res, cfg, n_train = work.options, filt.result, filt.config, filt.n_train
    after = work.stages[-1]
    e_filter = (filt.prediction[n_train:] - hold.p).norm(dim=-1)
    nis = res.nis[0, :n_train]
    work.effects.append(
        _integrated_record(
            work,
            after,
            params={
                "model": "network",
                "hidden": opts.network.hidden,
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
    work.note(
        f"integrated ANN-EKF: held-out RMSE [mm] after {text}, after the filter {after.rmse * 1e3:.4f} "
        f"(final model); the filter's own test-phase prediction {_rmse(e_filter) * 1e3:.4f}; mean NIS "
        f"{float(nis.mean()):.2f} (3 expected)"
    )


def _errors(model: MeasurementModel, m: Measurements) -> Tensor:
    return errors(model, m, trajectory=True)


_rmse = S.rmse


def integrate_adaptive(
    work: StageWork,
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
    ``predict`` reloads it like any work.

    ``setting`` (default ``Setting("adaptive")``): its ``hidden`` and ``gain`` set the random features (more and
    sharper features fit more, fewer and smoother ones extrapolate more gently), ``sigma_field`` the prior of the
    output layer (the field's expected RMS): the regularisation settings :func:`integrate_selected` chooses among
    on validation samples.
    ``scripts/integrated_trajectory.py`` measures the engines on simulated trajectories (docs/integrated.md,
    *The engines*).
    Steps: :func:`_adaptive_pass` (the filter), :func:`_install_adaptive` (the final model),
    :func:`_record_adaptive` (the report's record).
    """
    with torch.no_grad():  # the kinematic calibration's prediction: the report's reference G
        kinematic = work.model(Context(q=torch.cat([train.q, hold.q])))
    s = setting or Setting("adaptive")
    start, net, res, cfg = _adaptive_pass(work, train, hold, s.hidden, s.gain, s.sigma_field)
    _install_adaptive(work, start, net, res)
    after = work.add_stage(StageName.INTEGRATED)
    nw = len(res.active)  # the state is [w[active]; t; (d); gamma]
    filt = IntegratedFilter(
        _as_ekf_result(res), torch.cat([train.p, hold.p]), kinematic, train.n, cfg, res.w, res.P[:nw, :nw], res.active
    )
    settings = {"hidden": s.hidden, "feature_gain": s.gain, "sigma_field_m": s.sigma_field}
    _record_adaptive(work, filt, res=res, net=net, hold=hold, after=after, settings=settings)
    return filt


def _adaptive_pass(
    work: StageWork, train: Measurements, hold: Measurements, hidden: int, gain: float, sigma_field: float
):
    """The adaptive filter over the training samples from the nominal geometry with a rigid fit's tracker pose and
    lever arm, then its test phase on ``hold``; returns the start robot, the network, the result, the config."""
    from torchcal.filter.adaptive import AdaptiveConfig, AdaptiveEKF, random_features

    opts, robot = work.options, work.model.robot
    start = _nominal_copy(robot)
    place_instrument_and_tool(start, train.q, train.p, station=train.station, probe=train.probe)
    cfg = AdaptiveConfig(
        sigma_tracker=opts.fit.sigma_tracker,
        sigma_joint=opts.fit.sigma_joint,
        rank_tol=opts.fit.rank_tol,
        sigma_field=sigma_field,
    )
    net = random_features(dof=robot.dof, hidden=hidden, gain=gain, seed=int(opts.seed) + 1, device=robot.device)
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


def _install_adaptive(work: StageWork, start, net: CorrectionNet, res) -> None:
    """The final model: the filter's geometry (instrument translation back-substituted) and its network."""
    with torch.no_grad():
        work.model.robot.load_state_dict(res.apply(start).state_dict())
        net.set_flat(res.w)
    work.model.add(LearnedEffect(net))


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
    work: StageWork, filt: IntegratedFilter, *, res, net: CorrectionNet, hold: Measurements, after, settings: dict
) -> None:
    """The adaptive engine's effect record (settings, the geometry with its sigmas, the filter's health) and note."""
    n_train = filt.n_train
    e_filter = (filt.prediction[n_train:] - hold.p).norm(dim=-1)
    nis = res.nis[:n_train]
    work.effects.append(
        _integrated_record(
            work,
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
    work.note(
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


#: the longest region gate the paper's engine is tried behind (in units of the joints' training spread)
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
        """Region-gate lengths tried on validation. The paper's engine is kept only behind a finite gate: its
        6-29-3 network, refined jointly with a geometry of its own, can beat geometry alone on every piece of the
        validation block and still extrapolate worse than geometry on the path's continuation, far from the joints
        it was fitted on; a gate bounds how far from them it acts (docs/integrated.md, *Paths it was not tuned
        on*)."""
        return (
            tuple(g for g in gating.GATE_LENGTHS if g <= EKF_LONGEST_GATE)
            if self.engine == "ekf"
            else gating.GATE_LENGTHS
        )

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


def _run_setting(work: StageWork, train: Measurements, hold: Measurements, setting: Setting) -> IntegratedFilter:
    if setting.engine == "ekf":
        return integrate(work, train, hold)
    return integrate_adaptive(work, train, hold, setting)


def _scratch(work: StageWork, model: MeasurementModel, train_idx: Tensor, holdout_idx: Tensor) -> StageWork:
    """A throw-away work for one candidate: its own copy of ``model``, ``train_idx`` its training set and
    ``holdout_idx`` its held-out set (rows of the run's data), its own records."""
    trial = StageWork(work.run.with_split(train_idx, holdout_idx), work.name, model=copy.deepcopy(model))
    trial.fits = list(work.fits)
    trial.add_stage(StageName.GEOMETRIC)
    return trial


def _gated(model: MeasurementModel, region: Tensor, length: float, fallback) -> MeasurementModel:
    """``model`` with its last (learned) effect behind a region gate falling back to ``fallback``."""
    # a new model around the same robot and effects (copy.copy of a Module would share its submodule table, and
    # replacing the effect there would wrap the original model's effect too)
    return MeasurementModel(
        model.robot, [*model.effects[:-1], gating.RegionGate(model.effects[-1], region, length, fallback=fallback)]
    )


def _not_selected(evidence: dict, why: str) -> Rejection:
    return Rejection("learned", None, {"selection": evidence}, name="integrated", reason=why, cause=Cause.SELECTION)


@dataclass(frozen=True)
class _Chosen:
    """The best candidate on validation: its setting, the gate length chosen, its validation errors, its row of the
    selection table, and the model and filter fitted on the fitting samples."""

    setting: Setting
    length: float
    errors: Tensor  # (n_validation,) m
    row: dict
    model: MeasurementModel
    filt: IntegratedFilter


def integrate_selected(
    work: StageWork, train: Measurements, hold: Measurements, *, settings: tuple[Setting, ...] = SETTINGS
) -> IntegratedFilter | None:
    """The ``integrated`` method that keeps only what validation supports: never worse than geometry by design.

    The training samples are split in time: the last block (:func:`torchcal.stats.validation_count` samples)
    validates, the samples before it fit; the block is at the end so that the choice is judged on how a model
    predicts the *continuation* of the path it was fitted on, which is what the held-out samples (and a user's
    next program) ask of it.
    Geometry alone (the kinematic calibration refitted on the fitting samples) and every ``settings`` candidate
    (an engine with its capacity and prior, fitted on the fitting samples, the validation block its test phase)
    predict the validation block. Each is also tried behind a :class:`~torchcal.effects.region.RegionGate` of
    the lengths in :data:`~torchcal.effects.region.GATE_LENGTHS` (no gate among them), which fades the
    prediction back to the kinematic calibration where the path leaves the joints the filter was trained on. The
    candidate with the lowest validation RMSE is kept only if it beats geometry alone by a one-sided paired test
    at ``work.options.levels.validation``, with the standard error inflated for the autocorrelation of
    neighbouring samples (:func:`torchcal.stats.paired_test`); it is then fitted again on all training samples
    (the held-out samples its test phase) with the gate length chosen. Otherwise the work ends with the geometric
    model and says why. A candidate must also beat geometry alone on the validation block with any one of its
    :data:`VALIDATION_PIECES` pieces left out (:func:`leave_one_piece_out`). The table of candidates goes into the
    report (the effect's or the rejection's ``evidence["selection"]``). The kept model predicts a standard
    deviation per sample, calibrated on the validation block (:func:`_attach_predictive_sigma`,
    ``evidence["predictive_sigma"]``; ``predict`` writes it as ``sx, sy, sz``).
    """
    opts = work.options
    n_fit = train.n - S.validation_count(train.n)
    fit, val = train.subset(slice(0, n_fit)), train.subset(slice(n_fit, None))
    geo = copy.deepcopy(work.model)
    solve(
        geo,
        fit,
        GEOMETRIC_GROUPS,
        opts.fit,
        "integrated: geometry on the fitting samples",
        trajectory=True,
        identifiability=work.identifiability,
    )
    e_geo = _errors(geo, val)
    table, best = _validate_settings(work, geo, fit, val, e_geo, settings)
    evidence = {
        "rule": f"lowest validation RMSE among the candidates better than geometry alone on the validation block "
        f"with any one of its {VALIDATION_PIECES} consecutive pieces left out, kept when it beats geometry alone by "
        f"a one-sided paired test (autocorrelation-corrected) at p < {opts.levels.validation}",
        "n_fit": fit.n,
        "n_validation": val.n,
        "candidates": table,
    }
    why = _why_not_chosen(best, e_geo, evidence, opts.levels.validation)
    if why is not None:
        return _keep_geometry(work, evidence, why)
    return _fit_chosen(work, train, hold, best, geo=geo, fit_val=(fit, val), evidence=evidence)


def _validate_settings(
    work: StageWork, geo: MeasurementModel, fit: Measurements, val: Measurements, e_geo: Tensor, settings
) -> tuple[list[dict], _Chosen | None]:
    """Every setting fitted on the fitting samples and judged on the validation block behind the gate length that
    predicts it best: the selection table (geometry alone first) and the best candidate that beats geometry alone
    with any one piece of the block left out (None where none does)."""
    table = [{"candidate": "geometry alone", "validation_rmse_mm": _rmse(e_geo) * 1e3}]
    best = None
    n_fit = fit.n
    for setting in settings:
        _console.info(f"integrated: validating {setting.name} on the last {val.n} training samples")
        trial = _scratch(work, geo, work.train_idx[:n_fit], work.train_idx[n_fit:])
        try:
            trial_filter = _run_setting(trial, fit, val, setting)
        except EstimationError as err:
            table.append({"candidate": setting.name, "failed": str(err)})
            continue
        length, gates = gating.choose_gate_length(
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
        if max(left_out) < 1.0 and (best is None or _rmse(e) < _rmse(best.errors)):
            best = _Chosen(setting, length, e, row, trial.model, trial_filter)
    return table, best


def _why_not_chosen(best: _Chosen | None, e_geo: Tensor, evidence: dict, alpha: float) -> str | None:
    """Why geometry alone is kept (None: the best candidate beats it by the paired test at ``alpha``); the test
    goes into ``evidence``."""
    if best is None:
        return "no candidate beats geometry alone on the validation block with any one of its pieces left out"
    test = S.paired_test(e_geo, best.errors, ordered=True)
    evidence.update(chosen=best.row["candidate"], test=test.to_dict())
    if _rmse(best.errors) < _rmse(e_geo) and test.p_value < alpha:
        return None
    return (
        f"the best candidate, {best.row['candidate']}, does not beat geometry alone on the validation block "
        f"({_rmse(e_geo) * 1e3:.4f} -> {best.row['validation_rmse_mm']:.4f} mm, p = {test.p_value:.2g})"
    )


def _keep_geometry(work: StageWork, evidence: dict, why: str) -> None:
    """The work ends with the geometric model: a rejection that says why, a note, the refit where asked; or with
    the nominal one where the kinematic calibration is no better than it on the held-out samples
    (:func:`_step_back_to_nominal`)."""
    work.rejections.append(_not_selected(evidence, why))
    work.note(f"integrated: geometry alone kept: {why}")
    if _step_back_to_nominal(work, evidence):
        return None
    if work.options.refits:
        evidence["refit"] = refit_geometry(work, work.identifiability)
    return None


def _step_back_to_nominal(work: StageWork, evidence: dict) -> bool:
    """Where geometry alone is kept and the kinematic calibration moved no geometric element (under the tolerance
    priors a short or narrow trajectory can hold them all at nominal), it is the nominal geometry with its instrument
    pose and lever arm fitted again, different from the ``nominal`` stage's only by where the solver stopped; it is
    kept only where it beats that stage on the held-out samples (a lower RMSE, judged on
    :data:`~torchcal.pipeline.holdout.GUARD_MIN_POSES` samples or more), else the work ends with the nominal model,
    refitted on all samples where asked: a method never ends worse than the simpler one it replaces. A kinematic
    calibration that moved its geometry is not judged so: the held-out samples of a path are one stretch of it, and
    on them the nominal robot can win where the calibrated geometry continues the path several times better
    (docs/narrow-campaigns.md). ``evidence["nominal_guard"]`` holds the comparison. Returns whether it stepped back."""
    run = work.run
    nominal = run.stage(StageName.NOMINAL)
    geometry = work.model.robot.groups().get("geometry")
    if geometry is not None and bool((geometry.delta.detach() != 0).any()):
        evidence["nominal_guard"] = {"passed": True, "rule": "not judged: the kinematic calibration moved its geometry"}
        return False
    if run.hold.n < GUARD_MIN_POSES:
        evidence["nominal_guard"] = {"passed": True, "n": run.hold.n, "rule": "too few held-out samples to judge"}
        return False
    kin, nom = _rmse(_errors(work.model, run.hold)), _rmse(_errors(nominal.model, run.hold))
    guard = evidence["nominal_guard"] = {
        "passed": kin < nom,
        "n": run.hold.n,
        "kinematic_rmse_mm": kin * 1e3,
        "nominal_rmse_mm": nom * 1e3,
        "rule": "the kinematic calibration's held-out RMSE below the nominal geometry's",
    }
    if guard["passed"]:
        return False
    work.model = copy.deepcopy(nominal.model)
    work.fits.append(next(f for f in run.fits if f.stage == StageName.NOMINAL))
    work.add_stage(StageName.NOMINAL)  # its held-out errors: the training fit's, before any refit sees them
    if work.options.refits:
        both = work.fitted_and_held_out
        stage = "refit: instrument and lever arm on all samples"
        fit = solve(work.model, both, ("instrument", "tool"), work.options.fit, stage, trajectory=True, identify=False)
        work.fits.append(fit)
        evidence["refit"] = {"n_samples": both.n, "model": "nominal", "status": fit.result.status}
    text = (
        f"integrated: the nominal geometry kept: the kinematic calibration is no better than it on the held-out "
        f"samples ({guard['kinematic_rmse_mm']:.5f} mm against the nominal's "
        f"{guard['nominal_rmse_mm']:.5f})"
    )
    work.note(text)
    _console.info(text)
    return True


def _fit_chosen(
    work: StageWork,
    train: Measurements,
    hold: Measurements,
    best: _Chosen,
    *,
    geo: MeasurementModel,
    fit_val: tuple[Measurements, Measurements],
    evidence: dict,
) -> IntegratedFilter | None:
    """The chosen candidate fitted again on all training samples behind its gate, with its predictive sigma; kept
    where it is not worse than geometry alone on the held-out samples, else geometry it is (None)."""
    setting, length = best.setting, best.length
    _console.info(f"integrated: {setting.name} chosen on validation; fitted again on all {train.n} training samples")
    # the kinematic calibration on all training samples, kept apart: the engines edit work.model's robot in place
    geometric = copy.deepcopy(work.model)
    kinematic = geometric.robot
    n_effects, n_stages = len(work.effects), len(work.stages)
    filt = _run_setting(work, train, hold, setting)
    record = work.effects[-1]
    length = _gate_on_holdout(
        work.model, train, hold, kinematic=kinematic, setting=setting, length=length, evidence=evidence
    )
    fit, val = fit_val
    sigma = _attach_predictive_sigma(
        work,
        filt,
        kinematic=kinematic,
        geo=geo,
        val_model=best.model,
        val_filter=best.filt,
        fit=fit,
        val=val,
        train=train,
        hold=hold,
        length=length,
    )
    record.params["support_gate_length"] = length
    record.evidence["selection"] = evidence
    record.evidence["predictive_sigma"] = sigma
    guard = guard_against_geometry(work.model, geometric, hold)
    evidence["holdout_guard"] = guard
    if guard["passed"]:
        if work.options.refits:
            record.evidence["refit"] = _refit_filter(work, setting, length, geometric, work.identifiability)
        return filt
    # the refit on all training samples is worse than geometry alone where neither was fitted: geometry it is (the
    # work's robot too, which the adaptive engine changed in place and the report exports)
    work.model = geometric
    del work.effects[n_effects:], work.stages[n_stages:]
    why = (
        f"{setting.name}, chosen on validation, is worse than geometry alone on the held-out samples once fitted "
        f"again on all training samples ({guard['geometry_rmse_mm']:.4f} -> {guard['rmse_mm']:.4f} mm)"
    )
    return _keep_geometry(work, evidence, why)


def _refit_filter(work: StageWork, setting: Setting, length: float, geometric: MeasurementModel, ida) -> dict:
    """The chosen filter fitted again on all samples, training and held-out (``Options.refit``), as the model
    ``work.model`` writes: the engine of ``setting`` on all of them (the paper's engine judges its joint refinement
    on its own last samples, as on the training samples), behind a gate of the chosen ``length`` around all of
    them that falls back to the geometry fitted again on all of them, with the predictive sigma's calibration of
    the fit on the training samples (scale, floor, fallback scale and growth) and the refit's own weight
    covariance. On a trajectory the held-out last samples are the nearest to the path's continuation; selection,
    held-out guard and the reported held-out errors are those of the fit on the training samples. A refit that
    fails (a diverging pass) keeps the training fit, and the note says so. Returns the report's evidence."""
    both = work.fitted_and_held_out
    _console.info(f"integrated: {setting.name} fitted again on all {both.n} samples, training and held-out")
    geo_all = copy.deepcopy(geometric)
    fit = geometry_on_all(work, geo_all, ida, "integrated: geometry on all samples (refit)")
    trial = _scratch(work, geometric, torch.cat([work.train_idx, work.holdout_idx]), work.holdout_idx[:0])
    try:
        filt = _run_setting(trial, both, both.subset(slice(both.n, None)), setting)
    except EstimationError as err:
        why = f"the refit on all {both.n} samples failed ({err}); the model written is the training fit"
        work.note(f"refit: {why}")
        return {"n_samples": both.n, "skipped": why}
    old = work.model.effects[-1]  # the training fit's gate, with the predictive sigma's calibration
    gate = P.predictive_gate(
        trial.model,
        filt.weight_cov,
        filt.weight_index,
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
    work.model = trial.model
    work.note(
        f"refit: the model written is {setting.name} fitted again on all {both.n} samples (training and held-out), "
        f"behind the same gate around all of them; the held-out errors reported are those of the same choice "
        f"fitted on the {len(work.train_idx)} training samples only"
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
    *,
    kinematic,
    setting: Setting,
    length: float,
    evidence: dict,
) -> float:
    """The gate length the final model keeps: the shorter of the one chosen on the validation block (``length``,
    the candidate fitted on the fitting samples) and the one the held-out samples choose for the final model fitted
    on all training samples (``model``, its learned effect not yet gated; the gate around the training samples,
    falling back to the kinematic calibration). Each block is one stretch of the path leaving the samples fitted,
    and a gate is kept only as long as both support: a gate longer than one of them chose lets the network act
    where that stretch showed it extrapolating worse than the shorter gate (docs/integrated.md, *Paths it was not
    tuned on*). Only shortens: the held-out samples never lengthen the gate, so the held-out
    guard that follows judges a model at most as far from geometry as validation chose. The table goes into
    ``evidence["gate_on_holdout"]``; with fewer held-out samples than validation pieces, ``length`` is kept."""
    if hold.n < VALIDATION_PIECES:
        return length
    chosen, gates = gating.choose_gate_length(
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


def _attach_predictive_sigma(
    work: StageWork,
    filt: IntegratedFilter,
    *,
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
    """Put the final model's learned effect behind its region gate with a predictive standard deviation.

    The scale factor is calibrated on the validation block with the candidate fitted on the fitting samples
    (``val_model``, ``val_filter``) behind the same gate falling back to geometry on the fitting samples (``geo``);
    the final gate falls back to the kinematic calibration on all training samples (``kinematic``). The network's
    error far from the region tends to its gate's fallback's residual scale ``s_far``: geometry on the fitting
    samples on the validation block for the candidate's gate, the kinematic calibration on the held-out samples for
    the final gate (without held-out samples, the former for both). The fallback's error and its growth with
    distance come from geometry's own residuals (:func:`_growth_residuals`). Here the models are fitted and their
    residuals taken; the calibration itself, scale, floor and the fallback's growth on both gates, is
    :func:`~torchcal.effects.predictive.calibrate_predictive_sigma`. Always a gate, an infinite one included (it
    changes no prediction): it carries the standard deviation. Returns the report's evidence (scale, coverage of
    2 sigma on validation and on the held-out samples, the rule, the variance's parts).
    """
    opts = work.options
    noise = P.observation_sigma(work.model.robot, train, opts.fit.sigma_tracker, opts.fit.sigma_joint)
    # each fallback's residuals beyond its own region: geometry on the fitting samples on the validation block,
    # the kinematic calibration (geometry on all training samples) on the held-out samples
    e_geo = P.residuals(geo, val)
    e_kin = P.residuals(MeasurementModel(kinematic, []), hold) if hold.n else None
    far = P.residual_scale(e_geo)
    ell = P.sigma_length(length)
    val_gate = P.predictive_gate(
        val_model, val_filter.weight_cov, val_filter.weight_index, fit.q, length, geo.robot, noise, far, ell
    )
    e_growth, d_growth = _growth_residuals(work, kinematic, e_geo, val, train, val_gate)
    validation = P.GatedBlock(val_gate, val_model.robot, val.q, P.residuals(val_model, val, val_gate))
    # each gate's far part is its own fallback's residual scale beyond that fallback's region: geometry's on the
    # validation block for the candidate; the kinematic calibration's on the held-out samples for the final model
    # (a geometry on all training samples, better determined than the one on fewer)
    far_final = far if e_kin is None else P.residual_scale(e_kin)
    gate = P.predictive_gate(
        work.model, filt.weight_cov, filt.weight_index, train.q, length, kinematic, noise, far_final, ell
    )
    # the final model's residuals where it was not fitted (its own P_w, its gate)
    holdout = P.GatedBlock(gate, work.model.robot, hold.q, P.residuals(work.model, hold, gate)) if hold.n else None
    evidence = P.calibrate_predictive_sigma(validation, gate, holdout, e_growth, d_growth, e_kin)
    work.model.effects[-1] = gate
    work.stages.pop()
    work.effects[-1].rmse_after_mm = work.add_stage(StageName.INTEGRATED).rmse * 1e3
    check = evidence["sigma_check"]
    if check["suspect"]:
        work.note(
            f"integrated: the predictive sigma reaches {check['max_sigma_mm']} mm, {check['ratio']} times the "
            "largest validation or held-out residual: the widening factor was set by samples where the network's "
            "part of the variance is nearly zero; treat the sx, sy, sz columns of predict as unreliable"
        )
    return evidence


def _growth_residuals(
    work: StageWork,
    kinematic,
    e_geo: Tensor,
    val: Measurements,
    train: Measurements,
    val_gate: gating.RegionGate,
) -> tuple[Tensor, Tensor]:
    """The residuals ``(N, 3)`` [m] and distances ``(N,)`` [spreads] the fallback's growth with distance is fitted
    on (:func:`~torchcal.effects.predictive.fallback_growth`): geometric models' residuals on samples after the ones
    each was fitted on, at their distance from those. Geometry on the fitting samples on the validation block
    (``e_geo``) reaches only a short way from the region; a path's continuation can leave it much further (a random
    walk), so geometry is also refitted on the first half of the training samples (from the kinematic calibration)
    and its residuals on the second half show how far geometry's residual grows over a longer stretch."""
    half = train.n // 2
    first, second = train.subset(slice(0, half)), train.subset(slice(half, None))
    ida = work.identifiability
    geo_half = MeasurementModel(copy.deepcopy(kinematic), [])
    stage = "integrated: geometry on the first half (sigma)"
    solve(geo_half, first, GEOMETRIC_GROUPS, work.options.fit, stage, trajectory=True, identifiability=ida)
    half_gate = gating.RegionGate(val_gate.inner, first.q, math.inf)  # only its distance to the first half is used
    e = torch.cat([e_geo, P.residuals(geo_half, second)])
    d = torch.cat([val_gate.distance(val.q), half_gate.distance(second.q)])
    return e, d


#: the engines of the integrated method (``Options.engine``)
ENGINES = {Engine.AUTO: integrate_selected, Engine.ADAPTIVE: integrate_adaptive, Engine.EKF: integrate}


def integrated_stage(run: CalibrationRun) -> StageResult:
    """The ``integrated`` method's filter on the trajectory, with the engine ``Options.engine`` names."""
    work = StageWork(run, "integrated")
    work.filter = ENGINES[run.options.integrated.engine](work, run.train, run.hold)
    return work.result()
