"""Re-stationing a calibrated run: a new instrument placement (and, where asked, lever arm) from a few points.

A robot calibrated once is measured again from another placement of the tracker (a total station moved on a
construction site, a second cell): the robot's calibration holds, only the instrument pose ``T_tracker_base`` (6
parameters) and, with another tool, the lever arm ``t_flange_probe`` (3 more) are new. :func:`fit_station` fits them
to three or more measured points with everything else held; :func:`restation` loads a run and fits its new
placement, and :func:`torchcal.report.station.write_station` writes the result as a run directory that ``predict``
and ``compensate`` use as they use the calibrated one. A run calibrated from several stations (and probes) is
re-stationed as a run of one placement and one probe (:func:`one_placement`).

The fit:

1. Closed-form start: the run's predictions in the robot base frame (geometry and effects) rigidly fitted to the
   points (:func:`~torchcal.estimate.rigid.rigid_fit`); with the lever arm free, the alternating tracker/lever fit
   (:func:`~torchcal.estimate.rigid.fit_instrument_and_tool`) on the geometry.
2. Conditioning: the identifiability analysis (:func:`~torchcal.estimate.identifiability.analyse`) of the free
   parameters at the points; a direction the points do not fix is an error that names it (it is never held
   silently: a placement is either determined or not).
3. Weighted LM (:func:`~torchcal.estimate.fit.solve`) over ``("instrument",)`` or ``("instrument", "tool")``, no
   priors; its covariance ``s0^2 N^-1`` (scaled by the fit's own variance factor: on real data the robot's remaining
   model error, not the tracker noise, sets the scatter of a few points).
4. The run's own parameter uncertainty carried into the new placement: with ``g`` the run's parameters that stay
   (covariance ``C_gg`` from ``covariance.pt``, the geometric elements its rows could not tell held at the robot's
   manufacturing tolerance: :func:`held_at_tolerance`) and ``A = -(J_s^T J_s)^-1 J_s^T J_g`` (whitened Jacobians at the
   points), the placement is ``s = s_noise + A g``, so ``C_ss = C_noise + A C_gg A^T`` and ``C_gs = C_gg A^T``;
   RUN2's ``covariance.pt`` holds the whole matrix, so ``predict``'s ``sx, sy, sz`` include the placement.
5. Checks: per-point residuals and leave-one-out errors (the point predicted by the placement fitted to the others,
   the linear formula ``(I - H_ii)^-1 r_i``); a point whose leave-one-out error exceeds :data:`OUTLIER_FACTOR` times
   what the run predicts is named; a chi-square test of the residuals against what the run predicts per point
   (the run's held-out RMSE as an isotropic model error plus the measurement noise).
6. The placement's predicted effect on accuracy: the placement's covariance carried to poses like the points
   (:data:`REGION_POSES` poses drawn uniformly, seeded, in the points' joint ranges within ``model.json``'s region,
   :func:`points_region`; the points themselves where the run has none), RMS and max of the position sigma, added in
   quadrature to the run's predictive sigma over the same poses.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchcal import _console
from torchcal.data import Measurements
from torchcal.effects import Context, MeasurementModel
from torchcal.errors import EstimationError, TorchcalError
from torchcal.estimate.covariance import ParameterCovariance, central_jacobian
from torchcal.estimate.fit import selection, solve
from torchcal.estimate.identifiability import analyse
from torchcal.estimate.lm import chi2_quantile
from torchcal.estimate.problem import FreeParameters, jacobian_of, residual_function, whitening
from torchcal.estimate.rigid import fit_instrument_and_tool, rigid_fit
from torchcal.robot import transforms as tf
from torchcal.use.conditions import load_conditions, require_torques, with_load_sigma
from torchcal.use.rundir import check_placement, load_covariance, load_model, load_trust, rows_of

Tensor = torch.Tensor
F64 = torch.float64

#: a point whose leave-one-out error exceeds this many times the run's predicted error per point is named
OUTLIER_FACTOR = 5.0
#: poses drawn in the points' region (:func:`points_region`) to carry the placement's covariance to
REGION_POSES = 500
#: how far [rad] beyond the cone of the points' tool axes a pose drawn to predict the placement's error may turn (5 deg)
CONE_MARGIN = math.radians(5.0)
#: the points' spread: the second singular value of the centred points over the first below this is "collinear"
COLLINEAR_RATIO = 1e-3
#: significance level of the chi-square test
ALPHA = 0.05
#: points whose median residual exceeds this many times the run's predicted error per point are refused (another robot,
#: other units: 4300 x for ur10 points on a ur5 run); a placement that fits worse than predicted is a warning (one of
#: 8 points 5 mm off: 22 x, the lever arm fitted; real data a few x)
MAX_RESIDUAL_FACTOR = 100.0


class StationError(EstimationError):
    """The points cannot fix the placement: too few, collinear, or a direction they leave free."""


@dataclass(frozen=True)
class StationOptions:
    """What :func:`fit_station` reads.

    ``sigma_tracker`` and ``sigma_joint`` weight the points where they carry no ``sx, sy, sz`` (the run's stochastic
    model by default); ``run_rmse`` is the run's model error [m] the points are tested against: the RMS over the
    points' region of its predictive sigma (:mod:`torchcal.estimate.trust`), or its held-out RMSE for a run
    written before that.
    """

    tool: bool = False
    sigma_tracker: float = 15e-6
    sigma_joint: float = math.radians(0.0005)
    run_rmse: float = 0.0
    rank_tol: float = 1e-3
    max_iter: int = 100
    stat_tol: float = 1e-6
    seed: int = 0
    # solve() reads these; a re-stationing has no priors: the points determine the placement or it is refused
    prior_length: float | None = None
    prior_angle: float | None = None
    prior_instrument: tuple[float, float] | None = None
    prior_lever: float | None = None


@dataclass
class Station:
    """A fitted placement: the model it was written into, its covariance and the checks."""

    T_tracker_base: Tensor  # (4, 4)
    t_flange_probe: Tensor  # (3,) [m]
    names: list[str]  # the fitted parameters
    covariance: Tensor  # (u, u) the placement's, the run's own uncertainty included [m, rad]
    covariance_noise: Tensor  # (u, u) from the points' scatter alone
    residuals: Tensor  # (N, 3) measured minus predicted [m]
    loo: Tensor  # (N,) leave-one-out error norm [m] (nan where a point is needed to fix the placement)
    lines: tuple[int, ...]
    chi_square: dict
    fit_status: str
    iterations: int
    sigma0_sq: float
    region_sigma_rms: float  # [m] RMS of the placement's position sigma over the points' region (points_region)
    region_sigma_max: float  # [m]
    region_source: str
    run_rmse: float  # [m]
    tool: bool
    run_covariance: ParameterCovariance | None = None  # RUN2's covariance.pt
    label: str | None = None  # the station the points' rows name (None: none)
    #: [m] the RMS over the same poses of predict's sigma of the re-stationed run (its whole covariance: the
    #: placement's correlation with the run's parameters included), where the run measured its trust; else None
    predicted_sigma: float | None = None
    #: the share of the load's sigma beyond the run's training that the points bear out (None: no such load)
    load_sigma_scale: float | None = None
    #: the factor the points' leave-one-out errors put on the predicted error (:func:`_loo_scale`; 1: none)
    loo_scale: float = 1.0
    warnings: list[str] = field(default_factory=list)

    @property
    def std(self) -> Tensor:
        return self.covariance.diagonal().clamp(min=0).sqrt()

    @property
    def predicted_rmse(self) -> float:
        """What predict's sigma of the re-stationed run gives over poses like the points (:attr:`predicted_sigma`), or
        where the run has no trust, the run's held-out RMSE and the placement's RMS sigma in quadrature [m]. The two
        parts apart overstate it where the placement absorbs a parameter the run held at its prior (a lever-arm
        component along a tool axis that never turned): each then carries that prior, and only together cancel."""
        if self.predicted_sigma is not None:
            return self.predicted_sigma
        return math.hypot(self.run_rmse, self.region_sigma_rms)

    def to_dict(self) -> dict:
        """report.json's and model.json's ``station`` block (SI units, and mm where the key says so)."""
        std = self.std.tolist()
        units = ["m" if n.endswith(("tx", "ty", "tz")) or n.startswith("tool.") else "rad" for n in self.names]
        res = self.residuals.norm(dim=-1)
        return {
            "n_points": len(self.residuals),
            "label": self.label,
            "lever_arm_fitted": self.tool,
            "T_tracker_base": self.T_tracker_base.tolist(),
            "t_flange_probe_m": self.t_flange_probe.tolist(),
            "parameters": [{"name": n, "unit": u, "std": s} for n, u, s in zip(self.names, units, std)],
            "covariance": self.covariance.tolist(),
            "covariance_points_only": self.covariance_noise.tolist(),
            "fit": {"status": self.fit_status, "iterations": self.iterations, "sigma0_sq": self.sigma0_sq},
            "points": [
                {
                    "line": int(line),
                    "residual_m": r.tolist(),
                    "residual_mm": float(e) * 1e3,
                    "leave_one_out_mm": None if not math.isfinite(float(lo)) else float(lo) * 1e3,
                }
                for line, r, e, lo in zip(self.lines, self.residuals, res, self.loo)
            ],
            "rmse_points_mm": float(res.square().mean().sqrt()) * 1e3,
            "chi_square": self.chi_square,
            "accuracy": {
                "run_rmse_mm": self.run_rmse * 1e3,
                "placement_sigma_rms_mm": self.region_sigma_rms * 1e3,
                "placement_sigma_max_mm": self.region_sigma_max * 1e3,
                "predicted_rmse_mm": self.predicted_rmse * 1e3,
                "predicted_from": "predict's sigma of the re-stationed run (its whole covariance)"
                if self.predicted_sigma is not None
                else "the run's held-out RMSE and the placement sigma in quadrature",
                "over": self.region_source,
                "load_sigma_scale": self.load_sigma_scale,
                "leave_one_out_scale": self.loo_scale,
            },
            "warnings": list(self.warnings),
        }


def _placement_var(model: MeasurementModel, free: FreeParameters, C: Tensor, ctx: Context) -> Tensor:
    """The variance ``(N,)`` [m^2] of the predicted position (all three axes) at ``ctx`` through the placement's
    covariance ``C``."""
    J = central_jacobian(model, free, ctx, torch.full((len(free.names),), 1e-6, dtype=F64, device=ctx.q.device))
    return torch.einsum("nau,uv,nav->n", J, C.to(J), J).clamp(min=0)


def placement_std(model: MeasurementModel, station: Station, ctx: Context) -> Tensor:
    """The position standard deviation ``(N,)`` [m] the placement's uncertainty causes at ``ctx``, for a ``model``
    that holds the ``station``'s placement."""
    groups = ("instrument", "tool") if station.tool else ("instrument",)
    sel, labels = selection(model, groups, {n: True for n in station.names})
    free = FreeParameters(model, sel, labels)
    return _placement_var(model, free, station.covariance, ctx).sqrt()


def _check_points(points: Measurements, tool: bool) -> None:
    n, where = points.n, f"{points.source}: " if points.source else ""
    need = 4 if tool else 3
    if n < need:
        what = (
            "the instrument pose and the lever arm (9 parameters) need at least 4 points"
            if tool
            else "the instrument pose (6 parameters) needs at least 3 points"
        )
        raise StationError(f"{where}{n} point{'s' if n != 1 else ''} given; {what}")
    c = points.p - points.p.mean(0)
    S = torch.linalg.svdvals(c)
    if float(S[0]) == 0.0:
        raise StationError(f"{where}the {n} points are one and the same point: measure points that span a volume")
    if float(S[1]) < COLLINEAR_RATIO * float(S[0]):
        raise StationError(
            f"{where}the {n} points are (nearly) collinear (spread {float(S[0]):.3g} along their line, "
            f"{float(S[1]):.3g} across it, singular values in m): a rotation about their line is not fixed; "
            "measure points that span a plane or a volume"
        )


def points_region(model: MeasurementModel, points: Measurements) -> Tensor | None:
    """The joint ranges ``(2, dof)`` a placement's predicted error is over: those of its points, within the run's
    calibrated region where the two overlap (a joint the points hold still stays where they hold it). A placement
    predicts the poses like its points; over the whole calibrated region a parameter the run held at its prior (a lever
    arm component the calibration never turned) spread its prior over poses the placement never makes: 760 mm
    predicted for placements that missed by 2-8 mm. None where the run stores no region."""
    region = model.region
    if region is None:
        return None
    q = points.q.to(region)
    lo, hi = q.min(0).values, q.max(0).values
    lo2, hi2 = torch.maximum(lo, region[0]), torch.minimum(hi, region[1])
    ok = lo2 <= hi2
    return torch.stack([torch.where(ok, lo2, lo), torch.where(ok, hi2, hi)])


def _region_ctx(model: MeasurementModel, points: Measurements, seed: int) -> tuple[Context, str]:
    """Poses like the points: drawn uniformly in the points' region (:func:`points_region`, seeded) whose tool axis
    stays within the cone of the points' tool axes (:data:`CONE_MARGIN` beyond it; joints drawn each on its own turn
    a tool that the points keep pointing one way, where a parameter the run could not see spreads its prior); the
    points themselves where fewer than a tenth of the draws stay, or where the run has no calibrated region."""
    from torchcal.use.rundir import tool_axis_cone

    region = points_region(model, points)
    if region is None:
        return Context.from_measurements(points, trajectory=False), "the points (the run stores no calibrated region)"
    if points.tau is not None:  # measured torques hold at the poses they were measured at, not at drawn ones
        return Context.from_measurements(points, trajectory=False), "the points (their measured joint torques)"
    g = torch.Generator().manual_seed(int(seed))
    u = torch.rand(REGION_POSES, model.robot.dof, generator=g, dtype=F64).to(region)  # CPU generator, moved
    q = region[0] + u * (region[1] - region[0])
    cone = tool_axis_cone(model.robot, points.q)
    if cone is not None:
        axis = torch.tensor(cone["axis"], dtype=F64, device="cpu")  # compared with the CPU tool axes z
        with torch.no_grad():
            z = model.robot(q)[:, :3, 2].to("cpu", F64)
        keep = torch.arccos((z @ axis).clamp(-1.0, 1.0)) <= cone["max_angle"] + CONE_MARGIN
        if int(keep.sum()) < REGION_POSES // 10:
            return Context.from_measurements(points, trajectory=False), (
                "the points (poses drawn in their joint ranges turn the tool beyond the points' orientations)"
            )
        q = q[keep.to(q.device)]

    def mean(x):  # effects in time or temperature: at the points' mean
        return None if x is None else x.mean().expand(len(q)).to(q)

    ctx = Context(q=q, t=mean(points.t), temperature=mean(points.temperature), **_drawn_load(points, len(q), g))
    return ctx, f"{len(q)} poses drawn uniformly in the points' joint ranges and tool orientations"


def _drawn_load(points: Measurements, n: int, g: torch.Generator) -> dict:
    """The payload (and its centre of mass) of ``n`` poses like the points: each a point's, drawn at random (seeded),
    so that a run whose compliance reads the payload predicts them at the load the points carry."""
    if points.payload is None:
        return {}
    pick = torch.randint(points.n, (n,), generator=g).to(points.payload.device)
    com = points.payload_com
    return {"payload": points.payload[pick], "payload_com": None if com is None else com[pick]}


def _weak_directions(J: Tensor, names: list[str], k: int = 2) -> str:
    """The least determined directions of the column-scaled ``J``, in words."""
    s = J.norm(dim=0).clamp(min=1e-300)
    _, S, Vh = torch.linalg.svd(J / s, full_matrices=False)
    out = []
    for i in range(1, min(k, len(S)) + 1):
        v = Vh[-i]
        top = v.abs().argsort(descending=True)[:3]
        out.append(
            " + ".join(f"{float(v[j]):+.2f} {names[j]}" for j in top)
            + f" (relative singular value {float(S[-i] / S[0]):.1e})"
        )
    return "; ".join(out)


def _start(
    model: MeasurementModel,
    points: Measurements,
    ctx: Context,
    groups: tuple[str, ...],
    opts: StationOptions,
    warnings: list[str],
):
    """Steps 1 and 2 of the module docstring: the closed-form start written into ``model``, and the identifiability
    analysis of the placement at the points (an instrument direction they do not fix is refused, a lever-arm one is
    held and named in ``warnings``)."""
    robot = model.robot
    # 1. closed-form start: the run's predictions in the base frame (its lever arm) rigidly fitted to the points
    W = whitening(model, ctx, points.sigma, opts.sigma_tracker, opts.sigma_joint)

    def rigid_start() -> None:
        with torch.no_grad():
            base = tf.transform_points(tf.invert(robot.T_tracker_base().detach()), model(ctx))
            try:
                robot.instrument.set_matrix(rigid_fit(base, points.p))
            except EstimationError as e:
                raise StationError(f"the points do not fix the instrument pose: {e}") from None

    def analysis():
        sel, labels = selection(model, groups)
        free = FreeParameters(model, sel, labels)
        J = jacobian_of(residual_function(model, free, ctx, points.p, W))(free.vector())
        return analyse(J, free.names, tol=opts.rank_tol), J, free.names

    rigid_start()
    # 2. conditioning: an instrument direction the points do not fix is refused; a lever-arm one is held at the run's
    ida, J, names = analysis()
    weak_inst = [f["name"] for f in ida.fixed if f["name"].startswith("instrument.")]
    if weak_inst:
        raise StationError(
            f"the {points.n} points do not fix {', '.join(weak_inst)}; weakest directions: "
            f"{_weak_directions(J, names)}; measure points that span a volume"
        )
    held = [f["name"] for f in ida.fixed]
    if held:
        warnings.append(
            f"the points do not fix {', '.join(held)} (weakest directions: {_weak_directions(J, names)}): held at "
            "the run's lever arm; the tool's orientation hardly changes between the points, so these components "
            "are indistinguishable from the instrument's position (predictions at the same tool orientation are "
            "not affected)"
        )
    elif opts.tool:  # the lever arm is determined: the alternating closed form from the run's lever arm
        with torch.no_grad():
            T, t, _ = fit_instrument_and_tool(robot(points.q), points.p, robot.t_flange_probe().detach())
            robot.tool.nominal.copy_(t)
            robot.tool.delta.zero_()
        rigid_start()
    return ida


def fit_station(
    model: MeasurementModel,
    points: Measurements,
    opts: StationOptions,
    run_covariance: ParameterCovariance | None = None,
    load_sigma: Tensor | None = None,
) -> Station:
    """Fit the instrument pose (and with ``opts.tool`` the lever arm) of ``model`` to ``points``; module docstring.

    Args:
        model: a run's loaded model (:func:`~torchcal.use.rundir.load_model`); its instrument pose (and lever arm)
            is overwritten, nothing else changes.
        points: ``q`` and ``p`` of three or more points (four with the lever arm), optional ``sigma``.
        opts: :class:`StationOptions`.
        run_covariance: the run's ``covariance.pt`` (None: the run's own uncertainty is left out).
        load_sigma: ``(N, 3)`` [m] the standard deviation a load beyond the run's training adds at each point
            (:func:`~torchcal.use.conditions.load_conditions`), in the chi-square test's expected error (None: 0).

    Raises:
        StationError: too few points, collinear points, or a direction of the placement they do not fix.
    """
    if points.dof != model.robot.dof:
        raise StationError(f"the points have {points.dof} joints but the run's robot has {model.robot.dof}")
    _check_points(points, opts.tool)
    robot = model.robot
    ctx = Context.from_measurements(points, trajectory=False)
    warnings: list[str] = []
    groups = ("instrument", "tool") if opts.tool else ("instrument",)
    ida = _start(model, points, ctx, groups, opts, warnings)  # 1. closed-form start, 2. conditioning
    # 3. LM
    fit = solve(model, points, groups, opts, "station", trajectory=False, identifiability=ida)
    res = fit.result
    free = fit.free
    try:
        C_noise = res.covariance
    except EstimationError:
        raise StationError(
            f"the points do not fix the placement (singular normal matrix); weakest directions: "
            f"{_weak_directions(res.jacobian, free.names)}"
        ) from None
    if res.redundancy <= 0 or not math.isfinite(res.sigma0_sq):
        C_noise = torch.linalg.inv(res.normal)
        warnings.append("no redundancy: the covariance is that of the stochastic model alone, untested")
    # 4. the run's own uncertainty carried into the placement
    Js_w, C_s, run_cov = _carry_run_uncertainty(model, free, ctx, fit.whitening, C_noise, run_covariance)
    # 5. residuals, leave-one-out, chi-square against what the run predicts
    r, loo, chi = _point_checks(model, points, ctx, fit.whitening, Js_w, opts, warnings, load_sigma)
    # 6. the placement's effect on accuracy over the points' region
    rctx, source = _region_ctx(model, points, opts.seed)
    var_r = _placement_var(model, free, C_s, rctx)
    return Station(
        T_tracker_base=robot.T_tracker_base().detach().clone(),
        t_flange_probe=robot.t_flange_probe().detach().clone(),
        names=list(free.names),
        covariance=C_s.detach(),
        covariance_noise=C_noise.detach(),
        residuals=r.detach(),
        loo=loo,
        lines=tuple(points.lines),
        chi_square=chi,
        fit_status=str(res.status),
        iterations=res.iterations,
        sigma0_sq=res.sigma0_sq,
        region_sigma_rms=float(var_r.mean().sqrt()),
        region_sigma_max=float(var_r.max().sqrt()),
        region_source=source,
        run_rmse=opts.run_rmse,
        tool=opts.tool,
        run_covariance=run_cov,
        warnings=warnings,
    )


def _carry_run_uncertainty(
    model: MeasurementModel,
    free: FreeParameters,
    ctx: Context,
    W: Tensor,
    C_noise: Tensor,
    run_covariance: ParameterCovariance | None,
) -> tuple[Tensor, Tensor, ParameterCovariance]:
    """Step 4 of the module docstring: the placement's covariance with the run's own uncertainty (``C_s``), RUN2's
    whole covariance, and the whitened placement Jacobian ``(3N, u)`` at the points (``W`` the points' whitening)."""
    Js_w = W @ central_jacobian(model, free, ctx, torch.full((len(free.names),), 1e-6, dtype=F64, device=ctx.q.device))
    Js_w = Js_w.reshape(-1, len(free.names))
    C_s, kept = C_noise, None
    if run_covariance is not None:
        refit = {e.name for e in free.entries}
        kept = _without(run_covariance, refit)
    if kept is not None and len(kept.labels):
        g_free = kept.free(model)
        C_gg = kept.matrix.to(Js_w)
        Jg_w = (W @ central_jacobian(model, g_free, ctx, C_gg.diagonal().clamp(min=0).sqrt())).reshape(
            -1, len(kept.labels)
        )
        A = -torch.linalg.solve(Js_w.T @ Js_w, Js_w.T @ Jg_w)
        C_s = C_noise + A @ C_gg @ A.T
        C_gs = C_gg @ A.T
        full = torch.cat([torch.cat([C_gg, C_gs], 1), torch.cat([C_gs.T, C_s], 1)], 0)
        run_cov = ParameterCovariance(
            kept.names + [e.name for e in free.entries],
            kept.index + [[int(i) for i in e.index] for e in free.entries],
            kept.labels + list(free.names),
            (0.5 * (full + full.T)).detach().cpu(),
        )
    else:
        run_cov = ParameterCovariance(
            [e.name for e in free.entries],
            [[int(i) for i in e.index] for e in free.entries],
            list(free.names),
            C_s.detach().cpu(),
        )
    return Js_w, C_s, run_cov


def _point_checks(
    model: MeasurementModel,
    points: Measurements,
    ctx: Context,
    W: Tensor,
    Js_w: Tensor,
    opts: StationOptions,
    warnings: list[str],
    load_sigma: Tensor | None = None,
) -> tuple[Tensor, Tensor, dict]:
    """Step 5 of the module docstring: the residuals ``(N, 3)`` [m], the leave-one-out errors ``(N,)`` [m] and the
    chi-square test against what the run predicts; points of another robot refused, outliers named in ``warnings``."""
    with torch.no_grad():
        r = points.p - model(ctx)
    n = points.n
    Jb = Js_w.reshape(n, 3, -1)
    Ninv = torch.linalg.inv(Js_w.T @ Js_w)
    rw = (W @ r.unsqueeze(-1)).squeeze(-1)
    loo = torch.full((n,), float("nan"), dtype=F64, device=r.device)
    eye = torch.eye(3, dtype=F64, device=r.device)
    for i in _console.progress(range(n), desc="station: leave-one-out"):
        H_ii = Jb[i] @ Ninv @ Jb[i].T
        M = eye - H_ii
        if float(torch.linalg.svdvals(M)[-1]) > 1e-8:
            e_w = torch.linalg.solve(M, rw[i])
            loo[i] = torch.linalg.solve(W[i], e_w).norm()
    sig = points.sigma if points.sigma is not None else torch.full_like(points.p, opts.sigma_tracker)
    var = sig.square() + opts.run_rmse**2 / 3.0  # the run's model error, isotropic, per axis
    if load_sigma is not None:  # and what a load beyond its training adds
        var = var + load_sigma.to(var).square()
    stat = float((r.square() / var).sum())
    dof = 3 * n - Js_w.shape[1]
    thr = chi2_quantile(1.0 - ALPHA, dof) if dof > 0 else float("nan")
    chi = {
        "statistic": stat,
        "dof": dof,
        "threshold": thr,
        "alpha": ALPHA,
        "passed": bool(dof > 0 and stat <= thr),
        "against": "the run's held-out RMSE (isotropic model error) and the points' measurement sigma",
    }
    if dof > 0 and not chi["passed"]:
        why = "the load or the robot changed"
        if not opts.tool:
            why = "another tool than the run's (tool=True, --tool), or the robot moved"
        warnings.append(
            f"the points fit worse than the run predicts (chi-square {stat:.3g} > {thr:.3g} with {dof} degrees of "
            f"freedom): a point measured wrongly, {why}"
        )
    expected = math.sqrt(float(var.sum(-1).mean()))  # per point: the run's model error, the noise, the load's
    _refuse_foreign(points, r, expected)
    for i in range(n):
        if math.isfinite(float(loo[i])) and float(loo[i]) > OUTLIER_FACTOR * expected:
            warnings.append(
                f"line {points.lines[i]}: the point is {float(loo[i]) * 1e3:.3g} mm from where the others place it "
                f"(more than {OUTLIER_FACTOR:g} times the {expected * 1e3:.3g} mm the run predicts); check it"
            )
    return r, loo, chi


def _refuse_foreign(points: Measurements, r: Tensor, expected: float) -> None:
    """Stop points whose residuals ``r (N, 3)`` [m] are :data:`MAX_RESIDUAL_FACTOR` times what the run predicts per
    point (``expected`` [m]), as ``calibrate`` stops a geometric fit far beyond its priors: the robot's calibration is
    held here, so data of another robot or in other units show as residuals, and a run written from them would
    predict nonsense with a warning only."""
    med = float(r.norm(dim=-1).median())  # the median: one point measured wrongly is a warning (named), not this
    if expected > 0 and med > MAX_RESIDUAL_FACTOR * expected:
        raise StationError(
            f"{points.source or 'the points'}: the {points.n} points fit the run's robot with a median residual of "
            f"{med * 1e3:.4g} mm, {med / expected:.0f} times the {expected * 1e3:.3g} mm the run predicts per point "
            f"(limit {MAX_RESIDUAL_FACTOR:g} x): points of another robot, in other units (length_unit=, "
            "angle_unit=; --length-unit, --angle-unit), joints in another order or sign, or another tool than the "
            "run's (tool=True, --tool)"
        )


def _without(cov: ParameterCovariance, names: set[str]) -> ParameterCovariance:
    """``cov`` restricted to the blocks not in ``names``."""
    keep_blocks = [k for k, n in enumerate(cov.names) if n not in names]
    starts, pos = [], 0
    for idx in cov.index:
        starts.append(pos)
        pos += len(idx)
    rows = [starts[k] + j for k in keep_blocks for j in range(len(cov.index[k]))]
    r = torch.tensor(rows, dtype=torch.long, device=cov.matrix.device)
    return ParameterCovariance(
        [cov.names[k] for k in keep_blocks],
        [list(cov.index[k]) for k in keep_blocks],
        [cov.labels[i] for i in rows],
        cov.matrix[r][:, r].clone(),
    )


def _run_numbers(report: dict) -> tuple[float | None, float | None, float]:
    """The run's stochastic model (tracker sigma [m] or None for per-point sigmas, joint sigma [rad]) and its held-out
    RMSE [m] from ``report.json``."""
    sm = report.get("stochastic_model") or {}
    st, sj = sm.get("tracker_sigma_m"), sm.get("joint_sigma_rad")
    rmse = report.get("rmse_after_mm")
    return (
        float(st) if isinstance(st, int | float) and st > 0 else None,
        float(sj) if isinstance(sj, int | float) and sj >= 0 else None,
        float(rmse) * 1e-3 if isinstance(rmse, int | float) and math.isfinite(rmse) and rmse >= 0 else 0.0,
    )


def read_report(run_dir: str | os.PathLike) -> dict:
    """The run's ``report.json`` (empty where it has none)."""
    from torchcal._inputs import load_json

    run_dir = Path(run_dir)
    path = run_dir / "report.json"
    if not path.exists():
        return {}
    report = load_json(path, "report.json", lambda m: TorchcalError(f"{run_dir}: report.json {m}"))
    if not isinstance(report, dict):
        raise TorchcalError(f"{run_dir}: report.json is not a JSON object")
    return report


def station_options(run_dir: str | os.PathLike, tool: bool = False, seed: int = 0) -> StationOptions:
    """:class:`StationOptions` with the run's stochastic model and held-out RMSE (``report.json``; defaults where it
    lacks them)."""
    st, sj, rmse = _run_numbers(read_report(Path(run_dir)))
    base = StationOptions()
    return StationOptions(
        tool=tool,
        sigma_tracker=base.sigma_tracker if st is None else st,
        sigma_joint=base.sigma_joint if sj is None else sj,
        run_rmse=rmse,
        seed=seed,
    )


def restation(
    run_dir: str | os.PathLike, points: Measurements, *, tool: bool = False, seed: int = 0, probe: str | None = None
):
    """Load the run, fit the placement; returns ``(model, meta, station)`` (nothing is written).

    The run becomes a run of one placement (:func:`one_placement`): the new placement replaces all of its stations,
    every probe keeps its lever arm (a new placement moves the instrument, not the nest). The points' rows name their
    probe (their ``probe`` column, or ``probe`` for all of them; neither: the run's first) and at most one station (its
    label is kept: rows that name another station are then refused by ``predict``).

    The points' load (``payload``, ``tau`` columns) is the run's compliance's to carry, as in ``calibrate``: it is never
    absorbed into the placement or the lever arm. A load beyond the run's training widens the error the points are
    tested against and the predicted error by what :func:`~torchcal.use.conditions.load_conditions` adds (scaled by
    what the points bear out: :func:`_with_load_scale`). Points that fit worse than predicted test a changed tool
    (:func:`_try_new_tool`); a moved robot base is the placement itself (one instrument pose, ``T_tracker_base``, is
    fitted either way)."""
    model, meta = load_model(run_dir)
    check_placement(meta, points, keys=("probe",))  # a new placement, the same probes
    require_torques(model, points, points.source or "the points")  # a compliance that reads them carries their load
    cov = held_at_tolerance(model, load_covariance(run_dir, model))
    points, label = _points_rows(model, points, probe, tool, run_dir)
    model, meta, cov = one_placement(model, meta, cov, label, _only(points, "probe"), tool=tool)
    points = rows_of(model, points)  # each point's probe in the re-stationed run's order
    opts = station_options(run_dir, tool, seed)
    sigma = _run_sigma(run_dir, model, meta, cov, points, seed)
    if sigma is not None:  # the run's model error at a new placement: predict's sigma over the region
        opts = dataclasses.replace(opts, run_rmse=sigma)
    start = copy.deepcopy(model)
    # the points' load is the run's compliance's to carry (each row's payload and torques in the model's context);
    # what it cannot carry beyond the run's training load widens the error expected per point, as predict's sigma
    lc = load_conditions(model, meta, points, points.source or "the points")
    load_sigma = lc.sigma if lc.note is not None else None
    try:
        station, refused = fit_station(model, points, opts, cov, load_sigma), None
    except StationError as e:  # points far off the run: another tool is one of the reasons it names
        if tool or model.robot.probes or "another tool than the run's" not in str(e):
            raise
        station, refused = None, e
    if not tool and not model.robot.probes and (station is None or not station.chi_square["passed"]):
        model, station = _try_new_tool(start, model, points, opts, cov, station, refused, load_sigma)
    station.label = label
    if lc.note is not None:
        station.warnings.append(lc.note.removeprefix("torchcal: warning: "))
        meta = _with_load_scale(meta, station, points, opts, load_sigma)
    tr = load_trust(run_dir, meta)
    if tr is not None and station.run_covariance is not None:
        ctx, _ = _region_ctx(model, points, seed)
        with torch.no_grad():
            sigma = tr.std(model, ctx, station.run_covariance)
            sigma = with_load_sigma(sigma, load_conditions(model, meta, ctx, "").sigma)
            pctx = Context.from_measurements(points, trajectory=False)
            at_points = with_load_sigma(
                tr.std(model, pctx, station.run_covariance), load_conditions(model, meta, pctx, "").sigma
            )
        station.loo_scale = _loo_scale(station, at_points)
        station.predicted_sigma = float(sigma.square().sum(1).mean().sqrt()) * station.loo_scale
    return model, meta, station


def held_at_tolerance(model: MeasurementModel, cov: ParameterCovariance | None) -> ParameterCovariance | None:
    """The run's covariance with the geometric elements its rows could not tell held at the robot's manufacturing
    tolerance (its file's ``tolerances:``, else the kinematic calibration's defaults), not at the wider prior of a
    geometric change (1 mm, 0.1 deg) the closed loop's fits hold them at
    (:func:`~torchcal.estimate.covariance.tolerance_bounded`). A placement with a new lever arm carries what the run
    held to poses it never saw in those directions: a wrist element at the loop's 0.1 deg moved a probe 20 mm further
    out by 0.1 mm on a simulated UR10 whose geometry was off by its tolerance, and the predicted error was twice the
    measured one. A kinematic run's covariance already holds them at the tolerance and is unchanged."""
    from torchcal.estimate.covariance import tolerance_bounded
    from torchcal.pipeline.options import FitSettings

    if cov is None:
        return None
    tol = getattr(model.robot, "tolerances", None)
    if tol is None:
        d = FitSettings()
        tol = (d.tolerance_length, d.tolerance_angle)
    if tol[0] is None or tol[1] is None:
        return cov
    return tolerance_bounded(cov, model, tol[0], tol[1])


def _loo_scale(station: Station, sigma: Tensor) -> float:
    """How far the points' own leave-one-out errors (each point predicted by the placement fitted to the others: the
    error at a pose like the points, measured) bear out the predicted sigma ``(N, 3)`` [m] at the points: 1 where
    ``3 sum(loo^2 / |sigma|^2)`` lies within the two-sided ``ALPHA`` band of a chi-square of ``3 n`` degrees of freedom,
    else the factor that brings it to the nearer end. The run's covariance carried to a new lever arm spreads what
    the run held at its priors (a wrist element 0.3 deg uncertain moves a probe 20 mm further out by 0.1 mm) where the
    robot may have none of that error: the points then say so (a 20 mm tool change on a simulated UR10: 0.12-0.15 mm
    predicted, 0.04 measured at the next rows, before the scale)."""
    ok = torch.isfinite(station.loo)
    n = int(ok.sum())
    if n < 5:  # too few to tell
        return 1.0
    t = 3.0 * float((station.loo[ok].square() / sigma[ok.to(sigma.device)].square().sum(-1).clamp(min=1e-300)).sum())
    lo, hi = chi2_quantile(ALPHA / 2, 3 * n), chi2_quantile(1 - ALPHA / 2, 3 * n)
    scale = math.sqrt(t / lo) if t < lo else math.sqrt(t / hi) if t > hi else 1.0
    if scale != 1.0:
        station.warnings.append(
            f"the points' leave-one-out errors (RMS {float(station.loo[ok].square().mean().sqrt()) * 1e3:.3g} mm) "
            f"are {'smaller' if scale < 1 else 'larger'} than the run predicts at them (RMS "
            f"{float(sigma.square().sum(-1).mean().sqrt()) * 1e3:.3g} mm): the predicted error is scaled by "
            f"{scale:.2g} to what they bear out (predict's sigma of the re-stationed run is the run's)"
        )
    return scale


def _try_new_tool(
    start: MeasurementModel,
    model: MeasurementModel,
    points: Measurements,
    opts,
    cov,
    station,
    refused=None,
    load_sigma: Tensor | None = None,
):
    """The points fit worse than the run predicts with its lever arm (or so far off that the fit was ``refused``):
    test the alternative of a changed tool (the lever arm fitted too, as with ``--tool``). Adopted where the points
    then fit as predicted (its chi-square test passes), or where the new lever arm explains most of the misfit
    (:func:`_tool_supported`: a load or a robot that also changed leaves the rest), said in a warning; else the
    placement stands with a warning that names what a new lever arm left (a refusal stands)."""
    alt_model = copy.deepcopy(start)
    try:
        alt = fit_station(
            alt_model, points, dataclasses.replace(opts, tool=True), _without(cov, ("robot.tool.delta",)), load_sigma
        )
    except StationError as e:  # too few points, or orientations that do not fix a lever arm
        if station is None:
            raise refused from None
        station.warnings.append(
            f"a changed tool could not be tested ({e}); if the tool changed, give tool=True (--tool)"
        )
        return model, station
    chi0, chi1 = None if station is None else station.chi_square, alt.chi_square
    before = "too far off to fit"
    if chi0 is not None:
        before = f"chi-square {chi0['statistic']:.3g} > {chi0['threshold']:.3g}"
    if chi1["passed"]:
        alt.warnings.insert(
            0,
            f"the points fit worse than the run predicts with its lever arm ({before}) and as predicted with a new "
            f"one (chi-square {chi1['statistic']:.3g} <= {chi1['threshold']:.3g}): the tool changed, its lever arm "
            "was fitted too (as with tool=True, --tool)",
        )
        return alt_model, alt
    if _tool_supported(chi0, chi1):
        alt.warnings.insert(
            0,
            f"the points fit worse than the run predicts with its lever arm ({before}); a new lever arm explains most "
            f"of it (chi-square {chi1['statistic']:.3g}, {chi1['threshold']:.3g} expected at most): the tool changed, "
            "its lever arm was fitted too (as with tool=True, --tool); the rest is more than a new placement and tool: "
            f"{_what_else(start, points)}",
        )
        return alt_model, alt
    if station is None:
        raise refused
    station.warnings.append(
        f"a new lever arm does not explain it either (chi-square {chi1['statistic']:.3g} > {chi1['threshold']:.3g}): "
        f"{_what_else(start, points)}"
    )
    return model, station


#: a new lever arm is supported by points that still fit worse than predicted where it removes at least this share of
#: their chi-square's excess over its degrees of freedom (and significantly: a chi-square test of 3 degrees of freedom)
TOOL_EXPLAINS = 0.9


def _tool_supported(chi0: dict | None, chi1: dict) -> bool:
    """Whether a new lever arm (chi-square ``chi1``) explains the misfit of the placement alone (``chi0``; None: so
    far off that it was refused, which a lever arm that fits explains)."""
    if chi0 is None:
        return True
    drop = chi0["statistic"] - chi1["statistic"]
    excess = chi0["statistic"] - chi0["dof"]
    return drop > chi2_quantile(1.0 - ALPHA, 3) and drop >= TOOL_EXPLAINS * excess


def _what_else(model: MeasurementModel, points: Measurements) -> str:
    """What a misfit beyond a new placement and tool may be, and what to give: the load where the points carry none
    and the run's compliance reads it."""
    from torchcal.effects.joint import Compliance, LumpedCompliance, TorqueCompliance

    reads_load = any(
        isinstance(e, (Compliance, TorqueCompliance)) or (isinstance(e, LumpedCompliance) and e.load)
        for e in model.effects
    )
    if points.payload is None and points.tau is None and reads_load:
        return (
            "the robot's load (the run's compliance reads each row's payload: give the points' payload column, "
            "kg, where the robot carries another load than in the calibration), its base or the robot itself "
            "changed; calibrate again from the run (prior=, --prior RUN) where that does not explain it"
        )
    return (
        "the robot, its load or its base changed beyond a new placement; calibrate again from the run (prior=, "
        "--prior RUN)"
    )


def _with_load_scale(meta: dict, station: Station, points: Measurements, opts, load_sigma: Tensor) -> dict:
    """``meta`` whose ``load`` carries ``sigma_scale``: how much of the sigma a load beyond the run's training adds
    (:func:`~torchcal.use.conditions.load_conditions`, a reference compliance where the run's model does not carry the
    load) the points, measured at that load, bear out. The largest ``s <= 1`` whose chi-square of the points'
    residuals against ``sigma^2 + run_rmse^2 / 3 + s^2 load_sigma^2`` is not below its lower ``ALPHA`` quantile (the
    points would call a larger sigma too wide); 1 where they bear out all of it. The re-stationed run's ``predict``
    and this placement's predicted error read it."""
    r2 = station.residuals.square()
    sig = points.sigma if points.sigma is not None else torch.full_like(r2, opts.sigma_tracker)
    var0, vl = sig.to(r2).square() + opts.run_rmse**2 / 3.0, load_sigma.to(r2).square()
    dof = int(station.chi_square["dof"])
    lo = chi2_quantile(ALPHA, dof) if dof > 0 else float("nan")

    def chi(lam: float) -> float:
        return float((r2 / (var0 + lam * vl).clamp(min=1e-300)).sum())

    if not math.isfinite(lo) or chi(1.0) >= lo:
        scale = 1.0
    elif chi(0.0) <= lo:
        scale = 0.0
    else:  # chi decreases with lam: bisect chi(lam) = lo
        a, b = 0.0, 1.0
        for _ in range(60):
            m = 0.5 * (a + b)
            a, b = (m, b) if chi(m) > lo else (a, m)
        scale = math.sqrt(b)
    if scale < 1.0:
        station.warnings.append(
            f"the points, measured at that load, fit as if the load moved the probe {scale:.2g} times as far as the "
            "reference compliance allows: the load's part of the predicted error (and of predict's sigma in the "
            "re-stationed run) is scaled by that"
        )
    load = dict(meta.get("load") or {"payload_kg": [0.0, 0.0], "payload_column": False, "tau_Nm": None})
    load["sigma_scale"] = scale
    station.load_sigma_scale = scale
    return {**meta, "load": load}


def _run_sigma(run_dir, model: MeasurementModel, meta: dict, cov, points: Measurements, seed: int) -> float | None:
    """The RMS over the points' region (:func:`points_region`) of the run's predictive sigma ``|(sx, sy, sz)|`` [m]
    (:mod:`torchcal.estimate.trust`); None for a run written before it."""
    tr = load_trust(run_dir, meta)
    if tr is None:
        return None
    ctx, _ = _region_ctx(model, points, seed)
    return float(tr.std(model, ctx, cov).square().sum(1).mean().sqrt())


def _points_rows(
    model: MeasurementModel, points: Measurements, probe: str | None, tool: bool, run_dir
) -> tuple[Measurements, str | None]:
    """The points with their probe indices in the run's order, and the label of the one station they name (None
    where they name none). Refuses a probe the run lacks, ``probe`` on a run of one probe or against the points'
    column, points of several stations, and ``tool`` on a run of several probes."""
    where = points.source or "the points"
    known = model.robot.probes
    if probe is not None and not known:
        raise StationError(
            f"{run_dir}: the run has a single probe (its lever arm is used); drop probe={probe!r} (--probe)"
        )
    if tool and known:
        raise StationError(
            f"{run_dir}: the run has probes {', '.join(known)} on one nest, each with its lever arm; tool=True "
            "(--tool) fits one new lever arm and cannot tell which probe it replaces: re-station without it (every "
            "probe's lever arm is kept), or calibrate the new tool"
        )
    stations = _names(points, "station")
    if len(stations) > 1:
        raise StationError(
            f"{where}: the points name {len(stations)} stations ({', '.join(stations)}); re-station one placement "
            "at a time (its points only)"
        )
    label = stations[0] if stations else None
    if probe is not None:
        named = _names(points, "probe")
        if named and set(named) != {probe}:
            raise StationError(
                f"{where}: probe={probe!r} (--probe) but the points' probe column names {', '.join(named)}"
            )
        if probe not in known:
            raise StationError(f"{run_dir}: probe {probe!r} is not one of the run's ({', '.join(known)})")
        idx = torch.zeros(points.n, dtype=torch.long, device=points.q.device)
        points = dataclasses.replace(points, probe=idx, probe_names=(probe,))
    # the station the points name is the new placement's label, one of the run's or a new one (the help's example)
    points = dataclasses.replace(points, meta=dict(points.meta), station=None, station_names=())
    rows_of(model, points)  # a probe the run lacks: refused with its file, line and column
    return points, label


def _names(points: Measurements, key: str) -> tuple[str, ...]:
    """The ``station`` or ``probe`` names the points' rows use."""
    index, names = getattr(points, key), getattr(points, f"{key}_names")
    return () if index is None else tuple(names[int(i)] for i in torch.unique(index))


def _only(points: Measurements, key: str) -> str | None:
    """The one station or probe name all the points' rows give (None: none, or several)."""
    names = _names(points, key)
    return names[0] if len(names) == 1 else None


def one_placement(
    model: MeasurementModel,
    meta: dict,
    cov: ParameterCovariance | None,
    label: str | None = None,
    probe: str | None = None,
    tool: bool = False,
) -> tuple[MeasurementModel, dict, ParameterCovariance | None]:
    """The run as a run of one instrument placement, to be re-stationed: the pose of station ``label`` (where the
    run has it, else its first) as the start (the points replace it), every probe's lever arm kept, no learned
    correction per station and probe (a new placement is none of theirs), and a fallback geometry that a learned
    correction fades to tied to the robot's base frame (:meth:`~torchcal.effects.region.RegionGate.fallback_to_base`:
    it moves with the instrument). The covariance keeps the geometry, the effects and the lever arms; the stations'
    rows go (the points refit the placement), and with ``tool`` the lever arm's (the points refit it too). With
    ``probe`` (the one probe the points name) that probe comes first:
    rows of a file without a ``probe`` column take the first, and at the new placement that is the points' probe."""
    from torchcal.effects.grouped import GroupedCorrection
    from torchcal.effects.region import RegionGate
    from torchcal.robot.model import Instrument

    robot = model.robot
    k = robot.stations.index(label) if label in robot.stations else 0
    T0 = robot.T_tracker_base(k).detach()
    one = copy.deepcopy(model)
    if robot.stations:
        one.robot.instrument = Instrument(T0.clone(), dtype=robot.dtype, device=robot.device)
    dropped = [i for i, e in enumerate(one.effects) if isinstance(e, GroupedCorrection)]
    for i in reversed(dropped):
        del one.effects[i]
    for e in one.effects:
        if isinstance(e, RegionGate):
            e.fallback_to_base(T0, station=k)
    meta = {k_: v for k_, v in meta.items() if k_ != "stations"}
    if isinstance(meta.get("labels"), dict):  # the new placement's label is the points' (meta["station"])
        meta["labels"] = {k_: v for k_, v in meta["labels"].items() if k_ != "station"}
    if probe in robot.probes and robot.probes.index(probe):
        cov = _probe_first(one, cov, robot.probes.index(probe))
        meta["probes"] = list(one.robot.probes)
    meta["effects"] = [{"class": type(e).__name__, **e.config()} for e in one.effects]
    if robot.stations or robot.probes or dropped:
        meta["restationed_from"] = {
            "stations": list(robot.stations),
            "probes": list(robot.probes),
            "dropped": ["a learned correction per station and probe"] if dropped else [],
        }
    return one, meta, _without(cov, ("robot.instrument.delta", *(("robot.tool.delta",) if tool else ())))


def _without(cov: ParameterCovariance | None, names: tuple[str, ...]) -> ParameterCovariance | None:
    """``cov`` less the blocks ``names``: what the points fit again (the placement, with ``--tool`` the lever arm)
    is theirs, not the run's; counted in the run's sigma too, it was counted twice."""
    if cov is None or not any(n in cov.names for n in names):
        return cov
    keep = [j for j, name in enumerate(cov.names) if name not in names]
    starts = [sum(len(i) for i in cov.index[:j]) for j in range(len(cov.names))]
    rows = [starts[j] + i for j in keep for i in range(len(cov.index[j]))]
    r = torch.tensor(rows, dtype=torch.long, device=cov.matrix.device)
    return ParameterCovariance(
        [cov.names[j] for j in keep],
        [[int(i) for i in cov.index[j]] for j in keep],
        [cov.labels[i] for i in rows],
        cov.matrix[r][:, r].clone(),
    )


def _probe_first(model: MeasurementModel, cov: ParameterCovariance | None, k: int) -> ParameterCovariance | None:
    """Move probe ``k`` of ``model`` (and of a learned correction's fallback geometry) to the front; the covariance's
    lever-arm rows follow (each probe's rows keep their names, their indices in the new order)."""
    from torchcal.robot.model import Tool

    order = [k] + [i for i in range(len(model.robot.probes)) if i != k]
    robots = [model.robot] + [e.fallback for e in model.effects if getattr(e, "fallback", None) is not None]
    for r in robots:
        old = r.tool
        if len(old.probes) != len(order):
            continue
        new = Tool(old.nominal[order].clone(), dtype=r.dtype, device=r.device, probes=[old.probes[i] for i in order])
        with torch.no_grad():
            new.delta.copy_(old.delta[order])
            new.mask.copy_(old.mask[order])
        new.delta.requires_grad_(old.delta.requires_grad)
        r.tool = new
    if cov is None or "robot.tool.delta" not in cov.names:
        return cov
    b = cov.names.index("robot.tool.delta")
    start = sum(len(i) for i in cov.index[:b])
    moved = sorted((order.index(int(i) // 3) * 3 + int(i) % 3, start + j) for j, i in enumerate(cov.index[b]))
    rows = list(range(start)) + [j for _, j in moved] + list(range(start + len(cov.index[b]), len(cov.labels)))
    r = torch.tensor(rows, dtype=torch.long, device=cov.matrix.device)
    index = [list(i) for i in cov.index]
    index[b] = [i for i, _ in moved]
    return ParameterCovariance(list(cov.names), index, [cov.labels[i] for i in rows], cov.matrix[r][:, r].clone())
