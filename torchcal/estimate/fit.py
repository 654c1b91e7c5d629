"""Fitting selected parameter groups of a measurement model, and the errors of a model on measurements.

The primitives the calibration pipeline (:mod:`torchcal.pipeline`) is built from: the rigid start
(:func:`place_instrument_and_tool`), the weighted least-squares fit of parameter groups with their
identifiability analysis (:func:`solve`), the names of the named effects' parameters
(:func:`effect_parameter_labels`, :func:`effect_parameters`) and the per-pose errors (:func:`errors`,
:func:`corrections`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Protocol

import torch

from torchcal.data import Measurements
from torchcal.effects import Context, MeasurementModel
from torchcal.effects.registry import NAMED_KINDS
from torchcal.errors import EstimationError
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.estimate.identifiability import Identifiability, analyse, preference_order, weak_after_fit
from torchcal.estimate.lm import SINGULAR_EIGENVALUE, FitStatus, LMResult, global_test, levenberg_marquardt
from torchcal.estimate.problem import (
    FreeParameters,
    jacobian_of,
    orientation_angle,
    orientation_function,
    orientation_whitening,
    prior_sigmas,
    residual_function,
    stack_functions,
    whitening,
)
from torchcal.estimate.rigid import fit_instrument_and_tool
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor
#: the groups a kinematic calibration fits
GEOMETRIC_GROUPS = ("geometry", "instrument", "tool")
#: Default standard deviation of a 6-D probe's measured orientation per axis [rad], where the data give none (srx, sry,
#: srz): 0.01 deg, a T-Mac's order of magnitude (the IPA Series B-D report a median near 0.001-0.01 deg)
SIGMA_ORIENTATION = 0.01 * torch.pi / 180.0
#: Prior standard deviation of a readings map's ratio [1]: a transmission or differential ratio is known to about
#: 0.1 % (a gear's tooth count is exact; a belt's or a cable drum's diameter is not), so the fit moves it only where the
#: data demand it
PRIOR_READINGS_RATIO = 1e-3


#: the endings after which the fitted values are unusable
FAILED = (FitStatus.DIVERGED, FitStatus.FAILED_SOLVE)


class FitOptions(Protocol):
    """The settings :func:`solve` reads (:class:`torchcal.pipeline.Options` has them all)."""

    sigma_tracker: float  # m per axis, when the data carry no sx, sy, sz
    sigma_joint: float  # rad
    rank_tol: float
    max_iter: int
    prior_length: float | None  # m
    prior_angle: float | None  # rad
    stat_tol: float
    # optional (read with getattr; absent means no prior): the lever arm's prior sigma [m] (prior_lever) and the
    # instrument pose's (prior_instrument: position [m], rotation [rad]), centred on the start
    # (place_instrument_and_tool); with them a fit holds what the data cannot determine (weak_after_fit)


@dataclass
class Fit:
    """One least-squares fit: what was free, the solver's result, the identifiability analysis."""

    stage: str
    result: LMResult
    free: FreeParameters
    identifiability: Identifiability | None = None
    global_test: dict = field(default_factory=dict)
    whitening: Tensor | None = None  # (N, 3, 3) the L_i^-1 the residuals were whitened with
    #: the parameters the analysis frees only because the data carry orientation (a 6-D probe): fixed by the same
    #: analysis of the position rows alone (the probe frame's own rotation, ``tool.r*``, not counted)
    orientation_only: list[str] = field(default_factory=list)
    n_orientation: int = 0  # rows whose orientation the fit used
    #: the factor the orientation rows' sigmas were multiplied by so that their variance factor matches the
    #: positions' (:func:`orientation_scale`) times :data:`ORIENTATION_LEAD`; 1 without orientation
    orientation_scale: float = 1.0
    #: the parameters held at their prior value after the fit (:attr:`Identifiability.prior_held`) beside the free
    #: ones, and the covariance ``(u + h, u + h)`` of both with the held ones' prior as their uncertainty
    #: (:func:`considered`); None where none is held
    consider: tuple[FreeParameters, Tensor] | None = None


def place_instrument_and_tool(
    robot: RobotModel,
    q: Tensor,
    p: Tensor,
    lever: Tensor | None = None,
    lever_prior: tuple[Tensor, float] | None = None,
    station: Tensor | None = None,
    probe: Tensor | None = None,
) -> float:
    """Fit the tracker pose and the lever arm for the robot's current geometry and write them into ``robot``.

    Closed form (:func:`~torchcal.estimate.rigid.fit_instrument_and_tool`): the start of every calibration.

    Args:
        robot: its instrument pose and the nominal lever arm are overwritten; the lever arm's correction is
            set to zero, so the lever arm is the fitted one.
        q: ``(N, dof)`` joint positions [rad].
        p: ``(N, 3)`` measured probe positions in the tracker frame [m].
        lever: initial lever arm ``(3,)`` [m] (default zero).
        lever_prior: ``(centre (3,) [m], sigma_noise^2 / sigma_prior^2)``: a MAP start whose lever arm keeps near
            ``centre`` where the poses do not fix it; the lever arm's nominal is then ``centre`` and its correction
            the fitted lever arm minus it, so that a prior on the correction (zero mean) is centred on ``centre``.

        station, probe: ``(N,)`` int64 station and probe of each row, where the robot has several
            (:attr:`~torchcal.robot.model.RobotModel.stations`, ``probes``): one pose per station and one lever arm
            per probe, by :func:`place_stations_and_probes`.

    Returns:
        The RMS residual of the fit [m].
    """
    if robot.stations or robot.probes:
        return place_stations_and_probes(robot, q, p, station, probe, lever=lever, lever_prior=lever_prior)
    with torch.no_grad():
        T, t, rms = fit_instrument_and_tool(robot(q), p, lever, lever_prior=lever_prior)
        robot.instrument.set_matrix(T)
        if lever_prior is None:
            robot.tool.nominal.copy_(t)
            robot.tool.delta.zero_()
        else:
            robot.tool.nominal.copy_(lever_prior[0])
            robot.tool.delta.copy_(t - lever_prior[0])
    return rms


def place_tool_rotation(robot: RobotModel, q: Tensor, r: Tensor) -> float:
    """Enable and fit the probe frame's orientation in the flange frame for the robot's current geometry and
    instrument pose, in closed form, and write it into ``robot`` (its correction zero): the start of a 6-D probe's
    calibration, after :func:`place_instrument_and_tool`.

    Each pose gives ``R_flange_probe,i = R_base_flange(q_i)^T R_tracker_base^T R_meas,i``; their chordal mean
    (the rotation nearest to their sum, by SVD) is the estimate.

    Args:
        q: ``(N, dof)`` joint readings.
        r: ``(N, 3)`` measured orientations (rotation vectors, tracker frame) [rad].

    Returns:
        The RMS angle between the poses' estimates and their mean [rad].
    """
    from torchcal.robot import transforms as tf

    with torch.no_grad():
        robot.enable_orientation()
        R_tb = robot.T_tracker_base()[:3, :3]
        Ri = robot(q)[:, :3, :3].transpose(1, 2) @ R_tb.T @ tf.so3_exp(r)
        U, _, Vh = torch.linalg.svd(Ri.sum(0))
        D = torch.eye(3, dtype=U.dtype, device=U.device)
        D[2, 2] = torch.sign(torch.linalg.det(U @ Vh))
        R = U @ D @ Vh
        robot.tool_rotation.set_matrix(R)
        return float(orientation_angle(R.expand_as(Ri), Ri).square().mean().sqrt())


#: alternations of :func:`place_stations_and_probes` at most (each lowers the same cost; it settles in a few)
PLACE_ROUNDS = 50


def place_stations_and_probes(
    robot: RobotModel,
    q: Tensor,
    p: Tensor,
    station: Tensor | None,
    probe: Tensor | None,
    lever: Tensor | None = None,
    lever_prior: tuple[Tensor, float] | None = None,
) -> float:
    """:func:`place_instrument_and_tool` with several stations or probes: one pose per station, one lever arm per
    probe, by alternating closed-form steps (as :func:`~torchcal.estimate.rigid.fit_instrument_and_tool`): each
    station's rotation by a rigid fit of its rows with the current lever arms, then every station's translation and
    every lever arm together by linear least squares (MAP towards ``lever_prior``'s centre where given). Each step
    lowers the same cost. Written into ``robot``; returns the RMS residual [m]."""
    from torchcal.estimate.rigid import rigid_fit

    n = len(q)
    S, P = max(1, len(robot.stations)), max(1, len(robot.probes))
    st = torch.zeros(n, dtype=torch.long, device=q.device) if station is None or S == 1 else station
    pr = torch.zeros(n, dtype=torch.long, device=q.device) if probe is None or P == 1 else probe
    with torch.no_grad():
        Tf = robot(q)
        Rf, pf = Tf[:, :3, :3], Tf[:, :3, 3]
        t = torch.zeros(P, 3, dtype=q.dtype, device=q.device)
        if lever is not None:
            t[:] = lever
        eye = torch.eye(3, dtype=q.dtype, device=q.device)
        Rs = torch.zeros(S, 3, 3, dtype=q.dtype, device=q.device)
        t0 = torch.zeros(S, 3, dtype=q.dtype, device=q.device)
        prev = None
        for _ in range(PLACE_ROUNDS):
            pb = (Rf @ t[pr].unsqueeze(-1)).squeeze(-1) + pf
            for s in range(S):
                rows = st == s
                try:
                    T = rigid_fit(pb[rows], p[rows])
                except EstimationError as e:  # name the station: the message alone names no file or placement
                    name = f"station {robot.stations[s]!r}" if robot.stations else "the instrument"
                    raise EstimationError(f"{name}: its training rows cannot fix its pose: {e}") from None
                Rs[s], t0[s] = T[:3, :3], T[:3, 3]
            # for fixed rotations, the translations and lever arms are jointly linear: p - R pf = t0_s + R Rf t_p
            u = 3 * S + 3 * P
            A = torch.zeros(n, 3, u, dtype=q.dtype, device=q.device)
            cols = torch.arange(3, device=q.device)
            A[torch.arange(n)[:, None], :, 3 * st[:, None] + cols] = eye.expand(n, 3, 3).transpose(1, 2)
            RRf = Rs[st] @ Rf
            A[torch.arange(n)[:, None], :, 3 * S + 3 * pr[:, None] + cols] = RRf.transpose(1, 2)
            b = p - (Rs[st] @ pf.unsqueeze(-1)).squeeze(-1)
            AtA = torch.einsum("nau,nav->uv", A, A)
            Atb = torch.einsum("nau,na->u", A, b)
            if lever_prior is not None:
                centre, ratio = lever_prior
                AtA[3 * S :, 3 * S :] += float(ratio) * torch.eye(3 * P, dtype=q.dtype, device=q.device)
                Atb[3 * S :] += float(ratio) * centre.to(Atb).repeat(P)
            x = torch.linalg.solve(AtA, Atb)
            t0, t = x[: 3 * S].reshape(S, 3), x[3 * S :].reshape(P, 3)
            r = (A @ x) - b
            cost = float(r.square().sum(-1).mean())
            if prev is not None and prev - cost <= 1e-12 * prev:
                break
            prev = cost
        for s in range(S):
            T = torch.eye(4, dtype=q.dtype, device=q.device)
            T[:3, :3], T[:3, 3] = Rs[s], t0[s]
            robot.instrument.set_matrix(T, s if robot.stations else None)
        centre = lever_prior[0].to(t) if lever_prior is not None else None
        tool = robot.tool
        if robot.probes:
            tool.nominal.copy_(t if centre is None else centre.expand(P, 3))
            tool.delta.copy_(torch.zeros_like(t) if centre is None else t - centre)
        else:
            tool.nominal.copy_(t[0] if centre is None else centre)
            tool.delta.copy_(torch.zeros_like(t[0]) if centre is None else t[0] - centre)
    return float(cost**0.5)


def prior_scales(model: MeasurementModel, opts: FitOptions) -> dict[str, float]:
    """A-priori standard deviations of the instrument pose's and the lever arm's corrections by parameter name
    (``opts.prior_instrument``, ``opts.prior_lever``; none where the options do not set them), and of every element
    a robot rebased on a prior run names in its ``prior_sigma`` (:mod:`torchcal.pipeline.prior`)."""
    out: dict[str, float] = {}
    inst, lever = getattr(opts, "prior_instrument", None), getattr(opts, "prior_lever", None)
    for info in model.robot.parameter_info():
        if info.group == "readings":
            out[info.name] = PRIOR_READINGS_RATIO
        elif info.group == "instrument" and inst is not None:
            out[info.name] = float(inst[0] if info.unit == "m" else inst[1])
        elif info.group == "tool_rotation":
            continue  # the probe frame's rotation: the closed-form start is no prior
        elif info.group == "tool" and lever is not None:
            out[info.name] = float(lever)
    # a robot rebased on a prior run (torchcal.pipeline.prior) carries each element's a-priori sigma about it
    out.update(getattr(model.robot, "prior_sigma", None) or {})
    return out


def _priors(model: MeasurementModel, free: FreeParameters, opts: FitOptions, groups: tuple[str, ...]) -> Tensor | None:
    """The prior standard deviations of ``free`` (geometry's when the geometry is fitted, the instrument pose's and
    the lever arm's), or None when there are none."""
    units = {}
    if opts.prior_length is not None and opts.prior_angle is not None and "geometry" in groups:
        units = {i.name: i.unit for i in model.robot.parameter_info() if i.group == "geometry"}
    ps = prior_sigmas(free, units, opts.prior_length, opts.prior_angle, prior_scales(model, opts))
    return ps if bool(torch.isfinite(ps).any()) else None


def _hold(model: MeasurementModel, names: list[str]) -> None:
    """Put the named robot parameters back at their prior value (a zero correction)."""
    where = {i.name: i for i in model.robot.parameter_info()}
    with torch.no_grad():
        for n in names:
            if n in where:
                model.robot.groups()[where[n].group].delta[where[n].index] = 0.0


#: rounds of :func:`weak_after_fit` and refit at most (each holds one correlated parameter, or the weak ones)
HOLD_ROUNDS = 6


def errors(model: MeasurementModel, m: Measurements, trajectory: bool) -> Tensor:
    """Norm of the position error per pose ``(N,)`` [m]."""
    with torch.no_grad():
        return (model(Context.from_measurements(m, trajectory=trajectory)) - m.p).norm(dim=-1)


def orientation_errors(model: MeasurementModel, m: Measurements, trajectory: bool) -> Tensor | None:
    """Angle between the predicted and the measured probe orientation ``(M,)`` [rad] of each row whose orientation is
    used (:attr:`Measurements.orientation_rows`: every row unless the screening left some out), or None where the
    data or the model carry no orientation."""
    if m.r is None or not model.robot.has_orientation:
        return None
    with torch.no_grad():
        ctx_r, R_measured, _ = _orientation_data(Context.from_measurements(m, trajectory=trajectory), m)
        return orientation_angle(model.orientation(ctx_r), R_measured)


def corrections(model: MeasurementModel, m: Measurements, trajectory: bool) -> Tensor:
    """What the model misses, in the robot base frame ``(N, 3)`` [m] (paper Eq. 22)."""
    with torch.no_grad():
        ctx = Context.from_measurements(m, trajectory=trajectory)
        pred = model(ctx)
        if model.robot.stations:  # each row back through its own station's rotation
            R = model.robot.instrument.rows(ctx.station)[:, :3, :3]
            return ((m.p - pred).unsqueeze(1) @ R).squeeze(1)
        return (m.p - pred) @ model.robot.T_tracker_base()[:3, :3]


def effect_parameter_labels(model: MeasurementModel) -> tuple[dict[str, Tensor], dict[str, list[str]]]:
    """Selection masks (all free) and element names of the named effects' parameters, e.g.
    ``effects.0.k`` -> ``["compliance(joint 2).k"]``."""
    sel, labels = {}, {}
    for i, e in enumerate(model.effects):
        if e.kind not in NAMED_KINDS:
            continue
        for pname, p in e.named_parameters(recurse=False):
            key = f"effects.{i}.{pname}"
            sel[key] = torch.ones(p.shape, dtype=torch.bool, device=p.device)
            n = p.numel()
            labels[key] = [f"{e.label()}.{pname}" + (f"[{k}]" if n > 1 else "") for k in range(n)]
    return sel, labels


def effect_parameters(model: MeasurementModel, index: int, fit: Fit) -> dict:
    """Estimates with standard deviations of the parameters of ``model.effects[index]`` from ``fit``: per element
    ``value``, ``std`` and ``unit`` (the effect's :meth:`~torchcal.effects.base.Effect.param_units`)."""
    _, labels = effect_parameter_labels(model)
    res = fit.result
    std = res.std
    pos = {n: i for i, n in enumerate(res.names)}
    out = {}
    for key, names in labels.items():
        if not key.startswith(f"effects.{index}."):
            continue
        pname = key.split(".")[-1]
        values = dict(model.named_parameters())[key].detach().flatten().tolist()
        unit = model.effects[index].param_units(model.robot).get(pname)
        for k, (name, v) in enumerate(zip(names, values)):
            short = pname + name[len(f"{model.effects[index].label()}.{pname}") :]
            i = pos.get(name)
            out[short] = {
                "value": v,
                "std": float(std[i]) if i is not None else None,
                **({} if unit is None else {"unit": unit[k] if isinstance(unit, list) else unit}),
                **({} if i is not None else {"note": "held fixed: not identifiable"}),
            }
    return out


def selection(
    model: MeasurementModel, groups: tuple[str, ...], keep: dict[str, bool] | None = None, effects: bool = False
) -> tuple[dict[str, Tensor], dict[str, list[str]]]:
    """Masks and element names of the free parameters: the robot's ``groups`` (their free elements, and of those
    only the ones ``keep`` marks True) and with ``effects`` the named effects' parameters (those ``keep`` does
    not mark False)."""
    sel, labels = {}, {}
    robot_groups = model.robot.groups()
    if "geometry" in groups and "readings" in robot_groups:  # the readings map's ratios are fitted with the geometry
        groups = (*groups, "readings")
    if "tool" in groups and "tool_rotation" in robot_groups:  # a 6-D probe's frame: part of the tool
        groups = (*groups, "tool_rotation")
    for g in groups:
        grp = robot_groups[g]
        mask = grp.mask.clone()
        if keep is not None:
            mask &= torch.tensor([keep.get(n, False) for n in grp.names], device=mask.device).reshape(mask.shape)
        sel[f"robot.{g}.delta"] = mask
        labels[f"robot.{g}.delta"] = grp.names
    if effects:
        esel, elab = effect_parameter_labels(model)
        for key, mask in esel.items():
            if keep is not None:
                mask = torch.tensor([keep.get(n, True) for n in elab[key]], device=mask.device).reshape(mask.shape)
            sel[key], labels[key] = mask, elab[key]
    return sel, labels


def solve(
    model: MeasurementModel,
    m: Measurements,
    groups: tuple[str, ...],
    opts: FitOptions,
    stage: str,
    *,
    trajectory: bool,
    identify: bool = True,
    effects: bool = False,
    identifiability: Identifiability | None = None,
    covariance: bool = True,
) -> Fit:
    """Weighted LM over the free elements of ``groups`` (identifiable ones only when ``identify``).

    ``covariance`` False: a fit judged by its solution and residuals alone (the closed loop's validation refits),
    whose result needs no normal matrix at the solution: one Jacobian fewer (``LMResult.normal`` is then None). A
    fit that analyses its own identifiability, or whose prior-held elements are considered, computes it anyway.

    With ``effects`` the parameters of the model's named effects (:data:`NAMED_KINDS`) are estimated
    jointly with the groups; in the identifiability analysis they come after the geometry, so an effect
    parameter that the geometry already explains is held at its current value.

    ``identifiability`` reuses an earlier analysis (that of the geometric fit) for the robot's
    parameters instead of analysing again: after a fit the nominally parallel axes of a UR arm are no
    longer exactly parallel, and a new analysis would free parameters that are only determined to
    1e-5 (``d3``, ``d4``), which turns the refit into a crawl along a flat valley.

    Priors: the geometry's (``opts.prior_length``, ``prior_angle``) when it is fitted, the instrument pose's and the
    lever arm's (:func:`prior_scales`) always, as pseudo-observations (MAP). With a fresh analysis, an instrument or
    lever-arm element the analysis holds goes back to its prior value, and after the fit
    :func:`~torchcal.estimate.identifiability.weak_after_fit` may hold more (posterior sigma above 0.71 of the
    prior's, or correlated beyond 0.999), each added to the analysis' ``fixed`` with its reason, and the fit is
    repeated (at most :data:`HOLD_ROUNDS` times); later solves that reuse the analysis keep them held.
    """
    ctx = Context.from_measurements(m, trajectory=trajectory)
    W = whitening(model, ctx, m.sigma, opts.sigma_tracker, opts.sigma_joint)
    Wr, scale, lead = _scaled_orientation_rows(model, ctx, m, opts, identifiability)
    sel, labels = selection(model, groups, effects=effects)
    free = FreeParameters(model, sel, labels)
    ida, orientation_only = identifiability, []
    if identifiability is not None:
        keep = dict(zip(ida.names, ida.free.tolist()))
        keep.update({n: True for n in free.names if n not in keep})  # effect parameters: checked when scored
        sel, labels = selection(model, groups, keep, effects=effects)
        free = FreeParameters(model, sel, labels)
    elif identify:
        ida, orientation_only = _analyse_fresh(model, free, ctx, m, W, Wr, opts, groups)
        sel, labels = selection(model, groups, dict(zip(free.names, ida.free.tolist())), effects=effects)
        free = FreeParameters(model, sel, labels)
    covariance = covariance or identifiability is None or bool(ida is not None and ida.prior_held)
    res = _lm(model, free, ctx, m, W, Wr, opts, groups, stage, lead, covariance=covariance)
    if Wr is not None and identifiability is None:
        res, Wr, scale, lead = _orientation_component(model, free, ctx, m, W, Wr, opts, groups, stage, res, scale)
    if identifiability is None and ida is not None:
        res, free = _hold_weak(model, free, ida, ctx, m, W, Wr, opts, groups, stage, lead, res, effects)
    n_orientation = Wr.shape[0] if Wr is not None else 0
    fit = Fit(stage, res, free, ida, global_test(res), W, orientation_only, n_orientation, scale)
    if ida is not None and ida.prior_held:
        fit.consider = considered(
            model, fit, lambda f, ps: _residuals(model, f, ctx, m, W, Wr, ps), opts, groups, effects
        )
    return fit


@dataclass
class Step:
    """One Gauss-Newton step of :func:`gauss_newton_step`: the whitened cost ``0.5 |r|^2`` before it, as its
    linearisation predicts after it, and as the model gives after it; ``rows`` residuals and ``u`` parameters."""

    cost_before: float
    cost_predicted: float
    cost_after: float
    rows: int  # residual rows (observations and priors), as LMResult.n_obs counts them
    u: int
    #: where the Jacobi-scaled normal matrix is singular (no step taken, the costs after it NaN): its smallest
    #: eigenvalue; NaN otherwise
    smallest: float = float("nan")
    hint: str = ""  # there, which parameters it cannot fix (:func:`null_space_hint`)

    @property
    def singular(self) -> bool:
        return not math.isnan(self.smallest)

    @property
    def bic(self) -> float:
        """The BIC of the stepped fit with the variance estimated, as the closed loop's refits give it."""
        n = max(self.rows, 1)
        return n * math.log(max(2.0 * self.cost_after, 1e-300) / n) + self.u * math.log(n)

    @property
    def agreement(self) -> float:
        """The cost's actual decrease over the predicted one (1: the model is linear along the step)."""
        gain = self.cost_before - self.cost_predicted
        return (self.cost_before - self.cost_after) / gain if gain > 0 else float("nan")


def gauss_newton_step(
    model: MeasurementModel,
    m: Measurements,
    groups: tuple[str, ...],
    opts: FitOptions,
    *,
    trajectory: bool,
    identifiability: Identifiability,
    effects: bool = True,
) -> Step | None:
    """One undamped Gauss-Newton step of the problem :func:`solve` would solve with ``identifiability`` (the same
    free elements, whitening and priors), from the model's current values; written into the model.

    A cheap stand-in for a refit that starts at the optimum of a nearby problem (a fitted model with an effect added
    at zero): its step is nearly the refit's. Where the Jacobi-scaled normal matrix is singular as the LM's first
    iteration judges it (:data:`~torchcal.estimate.lm.SINGULAR_EIGENVALUE`) no step is taken (``Step.singular``);
    None, the model unchanged, where the step's cost is not finite.
    """
    ctx = Context.from_measurements(m, trajectory=trajectory)
    W = whitening(model, ctx, m.sigma, opts.sigma_tracker, opts.sigma_joint)
    Wr, _, _ = _scaled_orientation_rows(model, ctx, m, opts, identifiability)
    keep = dict(zip(identifiability.names, identifiability.free.tolist()))
    sel, labels = selection(model, groups, effects=effects)
    keep.update({n: True for n in FreeParameters(model, sel, labels).names if n not in keep})
    sel, labels = selection(model, groups, keep, effects=effects)
    free = FreeParameters(model, sel, labels)
    fun = _residuals(model, free, ctx, m, W, Wr, _priors(model, free, opts, groups))
    x = free.vector().detach()
    r = fun(x).detach()
    J = jacobian_of(fun)(x).detach()
    N = J.T @ J
    d = N.diagonal()
    s = torch.where(d > 0, d.clamp(min=1e-300).rsqrt(), torch.ones_like(d))
    Ns = N * s[:, None] * s[None, :]
    eye = torch.eye(len(x), dtype=x.dtype, device=x.device)
    before = 0.5 * float(r.square().sum())
    if int(torch.linalg.cholesky_ex(Ns - SINGULAR_EIGENVALUE * eye)[1]) != 0:  # as the LM's first iteration judges it
        nan = float("nan")
        hint = null_space_hint(SimpleNamespace(normal=N, names=free.names))
        return Step(before, nan, nan, len(r), len(x), smallest=float(torch.linalg.eigvalsh(Ns)[0]), hint=hint)
    L, info = torch.linalg.cholesky_ex(Ns)
    if int(info) != 0:
        return None
    dx = s * -torch.cholesky_solve(((J.T @ r) * s)[:, None], L)[:, 0]
    r_new = fun(x + dx).detach()
    after = 0.5 * float(r_new.square().sum())
    if not math.isfinite(after):
        return None
    free.assign(x + dx)
    return Step(before, 0.5 * float((r + J @ dx).square().sum()), after, len(r), len(x))


def _scaled_orientation_rows(model, ctx, m, opts: FitOptions, identifiability):
    """The orientation rows' whitening (None without orientations) and their variance component ``scale`` and
    ``lead``: estimated by a fit that analyses its own identifiability (the nominal and geometric fits, a refit),
    reused by the fits that take that analysis (the closed loop's)."""
    Wr = _orientation_rows(model, ctx, m, opts)
    scale, lead = 1.0, 1.0
    if Wr is not None and identifiability is not None:
        scale = getattr(model.robot, "orientation_scale", 1.0)
        lead = getattr(model.robot, "orientation_lead", 1.0)
    if Wr is not None:
        Wr = Wr / scale
    return Wr, scale, lead


def _analyse_fresh(model, free, ctx, m, W, Wr, opts: FitOptions, groups):
    """A fresh identifiability analysis of ``free``: ``(analysis, the parameters only the orientation rows make
    estimable)``; an instrument or lever-arm element it holds goes back to its prior value."""
    orientation_only: list[str] = []
    fun = _residuals(model, free, ctx, m, W, Wr)
    J = jacobian_of(fun)(free.vector())
    ps = _priors(model, free, opts, groups)  # the identifiability tolerance from the noise and the priors
    ida = analyse(J, free.names, preference_order(free.names), tol=opts.rank_tol, prior_sigma=ps)
    if Wr is not None:  # what the orientation rows make estimable: the same analysis of the position rows alone
        pos = analyse(J[: 3 * m.n], free.names, preference_order(free.names), tol=opts.rank_tol, prior_sigma=ps)
        rotation = {i.name for i in model.robot.parameter_info() if i.group == "tool_rotation"}
        orientation_only = [
            n for n, a, b in zip(free.names, ida.free.tolist(), pos.free.tolist()) if a and not b and n not in rotation
        ]
    # an instrument or lever-arm element the data cannot fix goes back to its prior's value (the start's)
    scaled = prior_scales(model, opts)
    back = [f for f in ida.fixed if f["name"] in scaled]
    _hold(model, [f["name"] for f in back])
    for f in back:
        f["reason"] = f["reason"].replace("held at its current value", "held at its prior value")
    # a geometric element the rows tell no better than its tolerance prior stays at its nominal value, its prior's
    # doubt kept in the run's covariance (:func:`considered`): a pose that moves it gets the tolerance's sigma
    at_nominal = _at_nominal(model)
    for f in ida.fixed:
        if f["name"] in at_nominal and "no better than its prior" in f["reason"]:
            f["reason"] = f["reason"].replace("held at its current value", "held near nominal by the prior")
            ida.prior_held.append(f["name"])
    return ida, orientation_only


def _at_nominal(model: MeasurementModel) -> set[str]:
    """The geometric elements whose correction is zero (their nominal value)."""
    geo = model.robot.groups().get("geometry")
    return {
        i.name
        for i in model.robot.parameter_info()
        if i.group == "geometry" and geo is not None and float(geo.delta.detach()[i.index]) == 0.0
    }


def _orientation_component(model, free, ctx, m, W, Wr, opts: FitOptions, groups, stage, res, scale):
    """Estimate the orientation rows' variance component from ``res`` and refit with it where it moves the weights
    by more than :data:`ORIENTATION_SCALE_TOL`; stores it on the robot. Returns ``(res, Wr, scale, lead)``."""
    vce = orientation_scale(res.residuals, m.n, Wr.shape[0])
    factor = vce * ORIENTATION_LEAD
    # the sigmas as applied against the variance component's: the variance factor counts the orientation rows at
    # the component's weight (also where the given sigmas were close enough to the lead's to be kept)
    if abs(math.log(factor)) > math.log(ORIENTATION_SCALE_TOL):
        scale, Wr = factor, Wr / factor
        lead = scale / vce
        res = _lm(model, free, ctx, m, W, Wr, opts, groups, stage, lead)
    else:
        lead = scale / vce
        res.variance_weights = _orientation_weights(res.residuals, Wr.shape[0], lead)
    model.robot.orientation_scale, model.robot.orientation_lead = scale, lead
    return res, Wr, scale, lead


def _hold_weak(model, free, ida, ctx, m, W, Wr, opts: FitOptions, groups, stage, lead, res, effects: bool):
    """Hold the instrument and lever-arm elements the fit left weak (:func:`weak_after_fit`) at their prior value
    and refit, at most :data:`HOLD_ROUNDS` times; each is added to ``ida``. Returns ``(res, free)``."""
    scaled = prior_scales(model, opts)
    units = {i.name: i.unit for i in model.robot.parameter_info()}
    for _ in range(HOLD_ROUNDS):
        ps = _priors(model, free, opts, groups)
        if ps is None or not any(n in scaled for n in free.names):
            break
        try:
            Q = res.cofactor
        except EstimationError:
            break  # a singular normal matrix: the structural analysis already had its say
        cand = torch.tensor([n in scaled for n in free.names], device=ps.device)
        found = weak_after_fit(free.names, Q, ps, cand, units, x=res.x, sigma0_sq=res.sigma0_sq)
        ida.hold(found)
        held = [h["name"] for h in found if h.get("held") is not False]
        if not held:
            break
        _hold(model, held)
        sel, labels = selection(model, groups, dict(zip(ida.names, ida.free.tolist())), effects=effects)
        free = FreeParameters(model, sel, labels)
        res = _lm(model, free, ctx, m, W, Wr, opts, groups, stage, lead)
    return res, free


def considered(model: MeasurementModel, fit: Fit, residuals, opts: FitOptions, groups, effects: bool):
    """The covariance of ``fit``'s free parameters together with those it held at their prior value, whose prior
    sigma ``s_h`` stays their uncertainty (a *consider* covariance, Schmidt): held, they still move the poses, and
    what the data made of the free ones depends on where they were held.

    With ``N`` the normal matrix (priors of the free ones included) at the solution, ``A = -N_ff^-1 N_fh`` is how the
    free parameters follow a held one; ``C_ff = s0^2 N_ff^-1 + A S A^T``, ``C_fh = A S``, ``C_hh = S``,
    ``S = diag(s_h^2)``. Along a combination the data cannot see (a lever arm along a tool axis that never turns,
    with every station's offset) ``A`` carries the held member's doubt to its partners so that predictions like the
    training poses keep their small sigma and poses that turn the axis get the prior's.

    Args:
        residuals: ``(free, prior_sigma) -> function`` of the fit's whitened residuals (:func:`_residuals`).

    Returns:
        ``(free and held parameters, covariance (u + h, u + h))``, or None where none of the held has a prior or the
        fit's normal matrix is singular.
    """
    free, res = fit.free, fit.result
    held = [n for n in fit.identifiability.prior_held if n not in free.names]
    sel, labels = selection(model, groups, {n: True for n in [*free.names, *held]}, effects=effects)
    both = FreeParameters(model, sel, labels)
    ps = _priors(model, both, opts, groups)
    held = [n for n in held if n in both.names and ps is not None and math.isfinite(float(ps[both.names.index(n)]))]
    if not held:
        return None
    dev = ps.device
    h = torch.tensor([both.names.index(n) for n in held], device=dev)
    f = torch.tensor([both.names.index(n) for n in free.names], device=dev)
    ps_free = ps.clone()
    ps_free[h] = float("inf")  # the held members' prior is their doubt below, not data
    J = jacobian_of(residuals(both, ps_free))(both.vector())
    try:
        C_free = res.covariance
    except EstimationError:
        return None
    A = -res.cofactor @ (J[:, f].T @ J[:, h])
    S = torch.diag(ps[h].square())
    C = torch.zeros(len(both), len(both), dtype=C_free.dtype, device=C_free.device)
    C[f[:, None], f[None, :]] = C_free + A @ S @ A.T
    C[f[:, None], h[None, :]] = A @ S
    C[h[:, None], f[None, :]] = (A @ S).T
    C[h[:, None], h[None, :]] = S
    return both, C


def fit_covariance(fit: Fit) -> ParameterCovariance | None:
    """The parameter covariance a run keeps of ``fit``: of its free parameters, and of those it held at their prior
    value where there are (:attr:`Fit.consider`); None where the fit's normal matrix is singular."""
    if fit.consider is None:
        return ParameterCovariance.from_fit(fit.free, fit.result)
    both, C = fit.consider
    index = [[int(i) for i in e.index] for e in both.entries]
    return ParameterCovariance([e.name for e in both.entries], index, list(both.names), C.detach().cpu())


#: the orientation rows are reweighted only when their variance factor differs from the positions' by more than this
#: ratio in sigma: below it the two groups' stochastic models agree as well as a few hundred rows can tell
ORIENTATION_SCALE_TOL = 1.5


#: the positions lead: the orientation rows' sigmas are this many times what their variance component gives (their
#: weight a ninth). What a calibration leaves is the model's own error, systematic in positions and orientations
#: alike; at the variance component's weight the orientation rows pull the parameters the positions determine towards
#: what suits the orientations (on the real UR10, Series D: held-out position 0.415 mm alone, 0.424 with the
#: orientations). At a ninth they still fix what only they determine (the probe frame's rotation, theta5) and keep
#: the position error the position-only one; at a hundredth they also stopped helping what they share with the
#: positions (a geometry carried to another placement, an update from a few rows; docs/real-data.md, *Full pose*).
ORIENTATION_LEAD = 3.0


def orientation_scale(residuals: Tensor, n: int, n_r: int | None = None) -> float:
    """The factor for the orientation rows' sigmas that gives them the positions' variance factor: ``sqrt(s_r^2 /
    s_p^2)`` of the whitened residuals ``(3 n [positions], priors, 3 n_r [orientations])`` (``n_r``: ``n`` unless
    some rows' orientations were left out).

    A 6-D probe reports its orientation's own noise (a T-Mac about 0.001 deg); what a calibration leaves is the model's
    error, in positions and orientations alike. Weighted by the instrument's sigmas alone, orientation rows then
    outweigh the positions many times over and the fit trades position accuracy for orientation; with the factor
    each group counts as much as its residuals show it can (a variance-component estimate, one step, redundancy
    shared in proportion to the rows)."""
    r = residuals.detach()
    s_p = float(r[: 3 * n].square().mean())
    s_r = float(r[-3 * (n if n_r is None else n_r) :].square().mean())
    if not (s_p > 0 and s_r > 0 and math.isfinite(s_p) and math.isfinite(s_r)):
        return 1.0
    return math.sqrt(s_r / s_p)


def _orientation_rows(model: MeasurementModel, ctx: Context, m: Measurements, opts: FitOptions) -> Tensor | None:
    """The whitening of the orientation rows ``(N, 3, 3)`` where the data and the model carry orientation (their
    own ``sigma_r``, else ``opts.sigma_orientation``, default :data:`SIGMA_ORIENTATION`), else None."""
    if m.r is None or not model.robot.has_orientation or not len(m.orientation_rows):
        return None
    sigma = getattr(opts, "sigma_orientation", None) or SIGMA_ORIENTATION
    ctx_r, _, sigma_r = _orientation_data(ctx, m, rotations=False)
    return orientation_whitening(model, ctx_r, sigma_r, sigma, opts.sigma_joint)


def _orientation_data(ctx: Context, m: Measurements, rotations: bool = True):
    """The context, the measured rotations ``(M, 3, 3)`` (None unless ``rotations``) and the orientation sigmas of
    the rows whose orientation is used (:attr:`Measurements.orientation_rows`: every row unless some were left
    out)."""
    from torchcal.robot import transforms as tf

    if m.all_orientations_used:
        return ctx, tf.so3_exp(m.r) if rotations else None, m.sigma_r
    idx = m.orientation_rows
    sigma_r = None if m.sigma_r is None else m.sigma_r[idx]
    return ctx.subset(idx), tf.so3_exp(m.r[idx]) if rotations else None, sigma_r


def _residuals(model, free, ctx: Context, m: Measurements, W: Tensor, Wr: Tensor | None, prior_sigma=None):
    """The whitened residuals of :func:`solve`: the positions (with the priors), then the orientations (``Wr``)."""
    fun = residual_function(model, free, ctx, m.p, W, prior_sigma)
    if Wr is None:
        return fun
    ctx_r, R, _ = _orientation_data(ctx, m)
    return stack_functions(fun, orientation_function(model, free, ctx_r, R, Wr))


def _lm(
    model,
    free: FreeParameters,
    ctx: Context,
    m: Measurements,
    W,
    Wr,
    opts: FitOptions,
    groups,
    stage: str,
    lead: float = 1.0,
    *,
    covariance: bool = True,
):
    """The weighted LM of :func:`solve` over ``free`` with its priors; the result is written into the model. With
    orientation rows weighed ``lead`` times below their variance component (:data:`ORIENTATION_LEAD`), their squared
    residuals count ``lead^2`` times in the variance factor (``LMResult.variance_weights``)."""
    fun = _residuals(model, free, ctx, m, W, Wr, _priors(model, free, opts, groups))
    res = levenberg_marquardt(
        fun,
        free.vector(),
        names=free.names,
        max_iter=opts.max_iter,
        stat_tol=opts.stat_tol,
        solution_jacobian=covariance,
    )
    if res.status in FAILED:
        hint = _readings_hint(model) or null_space_hint(res)
        raise EstimationError(f"{stage}: least squares {res.status}: {res.message}{hint}")
    if Wr is not None and lead != 1.0 and res.residuals is not None:
        res.variance_weights = _orientation_weights(res.residuals, Wr.shape[0], lead)
    free.assign(res.x)
    return res


def _readings_hint(model: MeasurementModel) -> str:
    """What to try when a robot whose readings are not its joints cannot be fitted: a reading of the other sign (a
    wrist whose controller counts the other way, left out of the ``readings:`` block) bends the chain where the data
    do not go, and the fit then finds no direction to move in."""
    if not model.robot.has_readings_map:
        return ""
    return (
        " (hint: the robot maps its readings to its joints; a reading of the other sign than the readings: block says "
        "leaves the fit without a solution: try the sign of each reading in the block, as for a wrong robot)"
    )


def null_space_hint(res) -> str:
    """Which parameters a singular normal matrix cannot fix, and the joints they belong to: a joint that turns the
    other way than the description says (a sign, an axis) bends the chain where the data do not go, and the fit then
    stops 'singular (rank deficient)' without naming a joint to check."""
    import re

    N = res.normal
    if N is None or not len(res.names) or not bool(torch.isfinite(N).all()):
        return ""
    d = torch.diagonal(N).clamp(min=1e-300).sqrt()
    Ns = N / d[:, None] / d[None, :]
    w, V = torch.linalg.eigh(Ns)
    tiny = w <= float(w[-1]) * 1e-10
    null = V[:, tiny] if bool(tiny.any()) else V[:, :1]  # the flattest direction where none is exactly null
    weight = null.square().sum(dim=1)
    order = [int(i) for i in torch.argsort(weight, descending=True) if float(weight[i]) > 0.1][:6]
    names = [res.names[i] for i in order] or [res.names[int(torch.argmax(weight))]]
    joints = sorted({int(m.group(1)) for n in names if (m := re.search(r"(\d+)(?:_joint)?(?:\.\w+)?$", n))})
    where = f" (joints {', '.join(map(str, joints))})" if joints else ""
    return (
        f" (hint: the data cannot fix {', '.join(names)}{where} together: check those joints' signs and axis "
        "directions in the robot description, and that the data cover them)"
    )


def _orientation_weights(residuals: Tensor, n: int, lead: float) -> Tensor:
    """``LMResult.variance_weights``: ``lead^2`` on the ``3 n`` orientation residuals (``n`` rows) that end the vector
    (:func:`orientation_scale`), 1 elsewhere."""
    w = torch.ones_like(residuals)
    w[-3 * n :] = lead**2
    return w


def prior_ratios(fit: Fit, model: MeasurementModel, opts: FitOptions) -> dict[str, float]:
    """How many prior standard deviations each fitted geometric correction of ``fit`` is: ``|delta_j| / sigma_j``.

    ``sigma_j`` is ``opts.prior_length`` [m] for a length and ``opts.prior_angle`` [rad] for an angle (the priors
    the fit was weighted with); parameters without a prior (instrument, tool, effects) are left out, and the result
    is empty when the options carry no priors.

    Returns:
        Element name (e.g. ``a2``, ``elbow_joint.tx``) -> ratio, for the free geometric elements of ``fit``.
    """
    if opts.prior_length is None or opts.prior_angle is None:
        return {}
    units = {i.name: i.unit for i in model.robot.parameter_info() if i.group == "geometry"}
    sigma = prior_sigmas(fit.free, units, opts.prior_length, opts.prior_angle)
    x = fit.result.x.to(sigma.device)
    return {n: float(x[i].abs() / sigma[i]) for i, n in enumerate(fit.free.names) if torch.isfinite(sigma[i])}
