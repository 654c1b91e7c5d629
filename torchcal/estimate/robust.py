"""Robust estimation: gross errors in the measured points found, named and left out of the fit.

A laser-tracker campaign holds a few rows that do not belong: a target slipped off its nest, the tracker
locked onto a reflection, a row typed in millimetres among rows in metres. Least squares spreads such a
row over every parameter (one 10 mm row moves the whole fit), so its own residual stays small and the
good rows' residuals grow: flagging rows by their residuals after a least-squares fit then names the
wrong rows. This module fits so that gross errors cannot pull, then tests every row.

Legend: ``r_i`` the whitened residual 3-vector of pose ``i`` (``L_i^-1 (f_i(x) - p_i)``, unit covariance
under the model), ``w_i`` its weight, ``J`` the whitened Jacobian, ``N = J^T J`` (kept rows and the
prior), ``Q = N^-1``. A pose is one group of three coordinates and is kept or rejected as a whole.

Method (:func:`robust_least_squares`):

1. **M-estimation by iteratively reweighted least squares** on the per-pose norm ``u_i = |r_i| / s`` with
   the robust scale ``s^2 = median(|r_i|^2) / median(chi2_3)``: Huber's weights first
   (``min(1, k / u_i)``, convex, so the start cannot trap it), then Tukey's redescending biweight
   (``(1 - (u_i / c)^2)^2``, 0 past ``c``), which gives a gross error no weight at all. Each round is a
   warm-started Levenberg-Marquardt solve (:func:`~torchcal.estimate.lm.levenberg_marquardt`) of the
   residuals multiplied by ``sqrt(w_i)``.
2. **Data snooping** (Baarda), starting from the rows the M-estimator kept: the least-squares fit of the
   kept rows, then per pose the test statistic ``T_i = r_i^T Q_vv,i^-1 r_i / s0^2`` with
   ``Q_vv,i = I - J_i Q J_i^T`` for a kept row (its redundancy block) and ``I + J_i Q J_i^T`` for a
   rejected one (the row predicted by the others). ``T_i ~ chi2_3`` when the row is good. The kept row
   with the largest ``T_i`` above the threshold is rejected (one at a time: a gross error inflates its
   neighbours' statistics, and removing the worst first keeps them), rejected rows that pass come back,
   and the kept rows are refitted, until nothing changes.

Threshold: the larger of the ``chi2_3`` quantile at ``1 - alpha / n`` (Bonferroni over the ``n`` poses),
so that a data set that follows its stochastic model loses a row with probability at most ``alpha``
(default 0.001) per screening, and ``GROSS_FACTOR^2``: a row is a gross error only when its error is also
at least ``GROSS_FACTOR`` (15) robust standard deviations (``sqrt(T_i) > 15``). The second bound is there
because an unmodelled effect is not normal noise: a warm-up drift or a joint-scale error leaves a long
systematic tail of residuals (up to about 10 robust standard deviations)
that the chi-square test alone would strip off as "outliers", taking away the very rows the closed loop
needs to find the effect. A 10 mm error lies hundreds of standard deviations out against a tracker's noise
and still about 30 against the half-millimetre residuals a real arm leaves, far past both bounds. Variance factor:
``s0^2 = max(1, median(T_i) / median(chi2_3))`` over the kept rows: the a-priori 1 of the stochastic
model, unless the data show a larger scatter (unmodelled effects on real arms), so a model that is only
approximately right does not turn its largest systematic residuals into "gross errors".

:func:`screen_geometric` applies this to a calibration: the geometry, tracker pose and lever arm fitted
robustly on the training poses (from the robust rigid start of
:func:`~torchcal.estimate.rigid.robust_instrument_and_tool`), then the held-out poses tested against that
model at the same family-wise level.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from torchcal.effects.base import Context
from torchcal.effects.model import MeasurementModel
from torchcal.errors import EstimationError, MeasurementFileError
from torchcal.estimate.fit import FAILED, SIGMA_ORIENTATION, FitOptions, selection
from torchcal.estimate.identifiability import analyse, preference_order
from torchcal.estimate.lm import LMResult, levenberg_marquardt
from torchcal.estimate.problem import FreeParameters, jacobian_of, prior_sigmas, residual_function, whitening
from torchcal.estimate.rigid import robust_instrument_and_tool
from torchcal.robot.transforms import so3_exp, so3_log

Tensor = torch.Tensor
F64 = torch.float64

#: family-wise probability that a clean data set loses a row in one screening
DEFAULT_ALPHA = 1e-3
#: a gross error lies at least this many robust standard deviations from the model (module docstring)
GROSS_FACTOR = 15.0
#: the largest median angle [deg] between the rows' probe frames in the flange frame (:func:`_screen_orientation`)
#: that orientations of a rigid probe may show: the probe's noise and the geometry's own errors give a fraction of a
#: degree (0.45 deg on the issue's real rows); orientations that are no rotation of the probe give tens of degrees
MAX_ORIENTATION_SPREAD_DEG = 10.0


def chi2_sf(x: float, k: int) -> float:
    """Survival function ``P(X > x)`` of the chi-square distribution with ``k`` degrees of freedom."""
    return float(torch.special.gammaincc(torch.tensor(k / 2.0, dtype=F64), torch.tensor(max(x, 0.0) / 2.0, dtype=F64)))


def chi2_isf(p: float, k: int) -> float:
    """The ``x`` with ``P(X > x) = p`` for chi-square with ``k`` degrees of freedom (bisection, exact to 1e-10)."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"chi2_isf needs 0 < p < 1, got {p}")
    lo, hi = 0.0, float(k)
    while chi2_sf(hi, k) > p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if chi2_sf(mid, k) > p:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-10 * hi:
            break
    return 0.5 * (lo + hi)


@dataclass
class Rejected:
    """One rejected row."""

    index: int  # row of the data screened (0-based)
    line: int  # file line of the row (``Measurements.lines``)
    statistic: float  # T_i / s0^2, chi2 with 3 degrees of freedom for a good row
    p_value: float  # of the row alone, before the Bonferroni correction
    size_mm: float  # |f_i(x) - p_i| of the robust fit, mm
    hint: str = ""  # a likely cause, e.g. a row in millimetres among rows in metres

    def to_dict(self) -> dict:
        return {
            "line": self.line,
            "size_mm": self.size_mm,
            "statistic": self.statistic,
            "p_value": self.p_value,
            **({"hint": self.hint} if self.hint else {}),
        }


@dataclass
class RobustResult:
    """What a robust fit returns; ``status``: converged, max_iterations, or too_many_rejected."""

    kept: Tensor  # (n,) bool, rows kept
    statistic: Tensor  # (n,) T_i / s0^2 at the final fit (chi2_3 for a good row)
    threshold: float  # chi2_3 quantile at 1 - alpha / n
    alpha: float  # family-wise level
    sigma0_sq: float  # variance factor the statistics are scaled by (module docstring)
    iterations: int  # reweighting rounds + snooping rounds
    status: str
    weights: Tensor  # (n,) the M-estimator's final weights in [0, 1]
    result: LMResult | None = None  # least squares of the kept rows
    rejected: list[Rejected] = field(default_factory=list)
    #: kept rows whose orientation (rx, ry, rz) is a gross error: their position is used, their orientation not
    orientation_dropped: list[Rejected] = field(default_factory=list)

    @property
    def orientation_dropped_index(self) -> Tensor:
        """Indices of the rows in :attr:`orientation_dropped` (0-based, of the data screened)."""
        return torch.tensor([x.index for x in self.orientation_dropped], dtype=torch.int64, device=self.kept.device)

    @property
    def n_rejected(self) -> int:
        return int((~self.kept).sum())


def _expand(w: Tensor, group: int, m_total: int) -> Tensor:
    """Per-residual factors: ``w`` repeated over each group's coordinates, 1 on the trailing (prior) rows."""
    wr = w.repeat_interleave(group)
    return torch.cat([wr, torch.ones(m_total - len(wr), dtype=w.dtype, device=w.device)])


def _weighted(fun: Callable[[Tensor], Tensor], sqrt_w: Tensor, group: int) -> Callable[[Tensor], Tensor]:
    """``fun``'s residuals times the groups' ``sqrt_w``; its Jacobian is ``fun``'s (analytic where it has one) with
    the same row factors."""
    cache = {}

    def factors(m: int) -> Tensor:
        if "s" not in cache:
            cache["s"] = _expand(sqrt_w, group, m)
        return cache["s"]

    def f(x: Tensor) -> Tensor:
        r = fun(x)
        return r * factors(r.shape[-1])

    def jacobian(x: Tensor) -> Tensor:
        J = jacobian_of(fun)(x)
        return J * factors(J.shape[0])[:, None]

    f.jacobian = jacobian
    return f


#: the ``stat_tol`` of a reweighting round (:func:`robust_least_squares`): a round only sets the weights, which read
#: each row's residual to about a tenth of the robust scale; a step that lowers the cost by less than this times the
#: variance factor moves the residuals by about ``sqrt(2 * ROUND_STAT_TOL)`` robust scales in all (spread over the
#: rows), and the next round goes on from there
ROUND_STAT_TOL = 1.0
#: the ``stat_tol`` of a snooping fit whose statistics only decide which row goes or comes back; once nothing changes
#: the fit is finished with the caller's ``stat_tol`` and the decision checked again on that solution
SNOOP_STAT_TOL = 1.0


def _chi2_median(k: int) -> float:
    return chi2_isf(0.5, k)


def snooping_statistics(
    fun: Callable[[Tensor], Tensor],
    x: Tensor,
    kept: Tensor,
    group: int = 3,
    jacobian: Callable[[Tensor], Tensor] | None = None,
) -> tuple[Tensor, float]:
    """Per-group statistics ``T_i = r_i^T Q_vv,i^-1 r_i`` (module docstring) and the robust variance factor.

    Args:
        fun: ``x -> r`` whitened residuals; the first ``n * group`` entries are the groups, the rest
            (a prior's pseudo-observations) always count.
        x: parameters ``(u,)`` of the least-squares fit of the kept groups.
        kept: ``(n,)`` bool.

    Returns:
        ``T (n,)`` unscaled, and ``median(T[kept]) / median(chi2_group)``.
    """
    T, med, _ = _statistics(fun, x, kept, group, jacobian)
    return T, med


def _statistics(fun, x: Tensor, kept: Tensor, group: int, jacobian=None) -> tuple[Tensor, float, Tensor]:
    """:func:`snooping_statistics` and the normal matrix ``N`` of the kept rows at ``x``."""
    n = len(kept)
    m = n * group
    J = (jacobian or jacobian_of(fun))(x).detach()
    r = fun(x).detach()
    rows = _expand(kept.to(F64), group, len(r)) > 0
    Jk = J[rows]
    N = Jk.T @ Jk
    d = N.diagonal()
    s = torch.where(d > 0, d.clamp(min=1e-300).rsqrt(), torch.ones_like(d))
    L, info = torch.linalg.cholesky_ex(N * s[:, None] * s[None, :])
    if int(info) != 0:
        raise EstimationError("robust fit: the normal matrix of the kept rows is singular (too many rows rejected?)")
    Q = torch.cholesky_inverse(L) * s[:, None] * s[None, :]
    Jp = J[:m].reshape(n, group, -1)
    H = Jp @ Q @ Jp.transpose(1, 2)
    sign = torch.where(kept, -1.0, 1.0).to(F64)[:, None, None]
    Qvv = torch.eye(group, dtype=F64, device=H.device) + sign * H
    rp = r[:m].reshape(n, group, 1)
    Lq, info = torch.linalg.cholesky_ex(Qvv)
    # a kept row of leverage ~1 (Q_vv ~ 0) has no redundancy and cannot be tested: statistic 0
    z = torch.linalg.solve_triangular(Lq, rp, upper=False)
    T = torch.where(info == 0, z.square().sum((1, 2)), torch.zeros(n, dtype=F64, device=z.device))
    med = float(T[kept].median()) / _chi2_median(group) if bool(kept.any()) else float("nan")
    return T, med, N


def robust_least_squares(
    fun: Callable[[Tensor], Tensor],
    x0: Tensor,
    n_groups: int,
    *,
    group: int = 3,
    names: list[str] | None = None,
    weights0: Tensor | None = None,
    alpha: float = DEFAULT_ALPHA,
    huber_rounds: int = 2,
    irls_rounds: int = 8,
    max_rounds: int = 30,
    max_iter: int = 100,
    round_iter: int = 10,
    stat_tol: float = 0.0,
    sigma0_floor: float = 1.0,
    max_reject_fraction: float = 0.5,
    gross: float = GROSS_FACTOR,
) -> RobustResult:
    """Fit ``0.5 |fun(x)|^2`` so that gross errors in groups of residuals do not pull (module docstring).

    Args:
        fun: ``x (u,) -> r (m,)`` whitened residuals; the first ``n_groups * group`` are the observations
            (group ``i`` = entries ``group*i .. group*i+group-1``), the rest are pseudo-observations of a
            prior that are never down-weighted.
        x0: start ``(u,)``.
        weights0: starting weights ``(n_groups,)`` (e.g. those of a robust start); default all 1.
        alpha: family-wise level of the snooping test (Bonferroni over the groups).
        huber_rounds: reweighting rounds with Huber's weights before Tukey's (none when ``weights0`` is given:
            a robust start needs no convex phase).
        irls_rounds: reweighting rounds at most; they stop earlier once the rows with zero weight stay the
            same and no weight moves by 0.05 (the weights only choose where the snooping starts).
        max_rounds: snooping rounds at most.
        max_iter: LM iterations of a snooping fit; ``round_iter`` those of a reweighting round.
        stat_tol: the :func:`levenberg_marquardt` stop of the last snooping fit; the reweighting rounds stop at
            :data:`ROUND_STAT_TOL` and the snooping fits that only decide at :data:`SNOOP_STAT_TOL` (when larger).
        sigma0_floor: the smallest variance factor the statistics are scaled by (module docstring).
        max_reject_fraction: stop rejecting (status ``too_many_rejected``) past this share of the groups.
        gross: the smallest ``sqrt(T_i)`` of a rejected group (module docstring); 0 for the test alone.

    Returns:
        :class:`RobustResult` (its ``rejected`` list empty: rows and lines are the caller's business).
    """
    n = int(n_groups)
    x = x0.detach().clone()
    w = torch.ones(n, dtype=F64, device=x0.device) if weights0 is None else weights0.detach().to(x0).clone()
    # a robust start's weights already exclude the gross errors: Huber's convex phase is for a plain start
    huber_rounds = huber_rounds if weights0 is None else 0
    x, w, irls_done = _reweight(fun, x, w, group, names, huber_rounds, irls_rounds, round_iter, stat_tol, sigma0_floor)
    threshold = max(chi2_isf(alpha / max(n, 1), group), gross**2)
    snoop = _snoop(
        fun, x, w > 0, group, names, threshold, max_rounds, max_iter, stat_tol, sigma0_floor, max_reject_fraction
    )
    return RobustResult(
        kept=snoop.kept,
        statistic=snoop.T / snoop.s0sq,
        threshold=threshold,
        alpha=alpha,
        sigma0_sq=snoop.s0sq,
        iterations=irls_done + snoop.rounds,
        status=snoop.status,
        weights=w,
        result=snoop.res,
    )


def _reweight(fun, x, w, group, names, huber_rounds, irls_rounds, round_iter, stat_tol, sigma0_floor):
    """The M-estimator's reweighting rounds (Huber's, then Tukey's): ``(x, weights, rounds run)``."""
    n = len(w)
    k_huber = math.sqrt(chi2_isf(0.1, group))  # Huber: full weight for the central 90 % of good rows
    c_tukey = math.sqrt(chi2_isf(1e-4, group))  # Tukey: zero weight past the 0.9999 quantile
    med = _chi2_median(group)
    rounds = 0
    for rnd in range(irls_rounds):
        rounds += 1
        # a round gives its solution only (the weights come from the residuals there): no Jacobian at the solution
        res = levenberg_marquardt(
            _weighted(fun, w.sqrt(), group),
            x,
            names=names,
            max_iter=round_iter,
            stat_tol=max(stat_tol, ROUND_STAT_TOL),
            solution_jacobian=False,
        )
        if res.status in FAILED:
            raise EstimationError(f"robust fit, reweighting round {rnd + 1}: least squares {res.status}: {res.message}")
        x = res.x
        with torch.no_grad():
            d2 = fun(x)[: n * group].reshape(n, group).square().sum(-1)
        s2 = max(float(d2.median()) / med, sigma0_floor)
        u = (d2 / s2).sqrt()
        if rnd < huber_rounds:
            w_new = torch.clamp(k_huber / u.clamp(min=1e-300), max=1.0)
        else:
            w_new = torch.where(u < c_tukey, (1.0 - (u / c_tukey).square()).square(), torch.zeros_like(u))
        change = float((w_new - w).abs().max())
        same_zeros = bool(((w_new == 0) == (w == 0)).all())
        w = w_new
        # the weights only choose where snooping starts: stop once Tukey's zero set is settled
        if rnd >= huber_rounds and (change < 1e-3 or (same_zeros and change < 0.05)):
            break
    return x, w, rounds


@dataclass
class _Snooping:
    """What data snooping ends with: the kept rows, their statistics and variance factor, and the last fit."""

    kept: Tensor
    T: Tensor
    s0sq: float
    status: str
    res: object
    rounds: int


def _snoop(fun, x, kept, group, names, threshold, max_rounds, max_iter, stat_tol, sigma0_floor, max_reject_fraction):
    """Data snooping from the rows the M-estimator kept: refit, reject the worst row over ``threshold`` and take
    back the rejected rows now under it, until neither happens. The fits stop at :data:`SNOOP_STAT_TOL` while they
    decide; the last one is then finished at ``stat_tol`` (the same rows: not a round of its own) and its statistics
    decide once more."""
    n = len(kept)
    status, res, T, s0sq = "max_iterations", None, torch.zeros(n, dtype=F64, device=x.device), float("nan")
    loose = max(stat_tol, SNOOP_STAT_TOL)
    rounds, finish = 0, False
    while finish or rounds < max_rounds:
        rounds += not finish
        if int((~kept).sum()) > max_reject_fraction * n:
            status = "too_many_rejected"
            break
        # no Jacobian at the solution from the fit: the statistics evaluate it there, and the normal matrix with it
        res = levenberg_marquardt(
            _weighted(fun, kept.to(F64), group),
            x,
            names=names,
            max_iter=max_iter,
            stat_tol=stat_tol if finish else loose,
            solution_jacobian=False,
        )
        if res.status in FAILED:
            raise EstimationError(f"robust fit, snooping: least squares {res.status}: {res.message}")
        x = res.x
        T, s0sq, res.normal = _statistics(fun, x, kept, group)
        s0sq = max(s0sq, sigma0_floor)
        z = T / s0sq
        back = ~kept & (z <= threshold)
        bad = kept & (z > threshold)
        if not bool(back.any()) and not bool(bad.any()):
            # a loose fit that stopped for another reason than its stat_tol is where the tight one would stop
            if finish or loose == stat_tol or "stat_tol" not in res.message:
                status = "converged"
                break
            finish = True
            continue
        finish = False
        kept = kept | back
        if bool(bad.any()):
            kept[int(torch.argmax(torch.where(bad, z, torch.zeros_like(z))))] = False
    return _Snooping(kept, T, s0sq, status, res, rounds)


# ---------------------------------------------------------------------------------------------------------
# a calibration's screening


@dataclass
class Screening:
    """The robust screening of a calibration's training and held-out poses (:func:`screen_geometric`)."""

    training: RobustResult
    holdout: RobustResult
    model: MeasurementModel  # the robust geometric fit (a copy; the caller's model is untouched)
    method: str
    gross: float = GROSS_FACTOR
    free: list[str] = field(default_factory=list)
    orientations_tested: bool = False  # the data carried orientations (rx, ry, rz), each tested

    def to_dict(self) -> dict:
        def part(r: RobustResult) -> dict:
            dropped = {
                "n_orientation_dropped": len(r.orientation_dropped),
                "orientation_dropped": [x.to_dict() for x in r.orientation_dropped],
            }
            return {
                "n": len(r.kept),
                "n_rejected": r.n_rejected,
                "threshold": r.threshold,
                "sigma0_sq": r.sigma0_sq,
                "status": r.status,
                "iterations": r.iterations,
                "rows": [x.to_dict() for x in r.rejected],
                **(dropped if self.orientations_tested else {}),
            }

        return {
            "method": self.method,
            "alpha": self.training.alpha,
            "statistic": "T = r' Qvv^-1 r / s0^2 per pose (x, y, z together), chi2 with 3 degrees of freedom "
            "for a good pose; rejected when T > max(chi2_3(1 - alpha / n), gross^2)",
            "gross": self.gross,
            "training": part(self.training),
            "holdout": part(self.holdout),
            "lines": [x.line for x in self.training.rejected + self.holdout.rejected],
        }


def _hint(measured: Tensor, predicted: Tensor) -> str:
    """A likely cause of a gross error from the ratio of the distances from the tracker."""
    ratio = float(measured.norm()) / max(float(predicted.norm()), 1e-12)
    if 300.0 < ratio < 3000.0:
        return (
            f"looks like millimetres: the point lies {ratio:.0f} times farther from the tracker than the model "
            f"predicts; convert the row to the file's unit (metres)"
        )
    if 1 / 3000.0 < ratio < 1 / 300.0:
        return (
            f"looks like metres: the point lies {1 / ratio:.0f} times closer to the tracker than the model "
            f"predicts; convert the row to the file's unit (millimetres)"
        )
    return ""


def _name_rows(res: RobustResult, m, pred: Tensor, file_unit_hint: bool = True) -> None:
    size = (pred - m.p).norm(dim=-1)
    for i in torch.nonzero(~res.kept).flatten().tolist():
        z = float(res.statistic[i])
        res.rejected.append(
            Rejected(
                index=i,
                line=int(m.lines[i]),
                statistic=z,
                p_value=chi2_sf(z, 3),
                size_mm=float(size[i]) * 1e3,
                hint=_hint(m.p[i], pred[i]) if file_unit_hint else "",
            )
        )
    res.rejected.sort(key=lambda x: x.line)


def _probe_frames(model: MeasurementModel, m) -> Tensor:
    """Each row's probe frame in the flange frame ``(N, 3, 3)`` as its measured orientation says: ``(R_tracker_base
    R_base_flange(q))^T R_measured``. One frame for every row of a rigid probe, up to the noise."""
    robot = model.robot
    R_tb = robot.instrument.rows(m.station if robot.stations else None)[..., :3, :3]  # each row's own station
    R_tf = R_tb @ robot(m.q)[..., :3, :3]
    return R_tf.transpose(-1, -2) @ so3_exp(m.r)


#: the fewest rows of one station and probe that :func:`_robust_start` fits robustly on their own: with fewer, one
#: gross row among them is not outvoted
MIN_GROUP_ROWS = 6


def _common_frame(R: Tensor, rounds: int = 5) -> Tensor:
    """A robust centre ``(3, 3)`` of the rotations ``R (N, 3, 3)``: the component-wise median of their rotation
    vectors about the current centre, a few times (a gross row moves a median by one rank, not by its size)."""
    centre = R[0]
    for _ in range(rounds):
        v = so3_log(centre.transpose(-1, -2) @ R)
        centre = centre @ so3_exp(v.median(dim=0).values)
    return centre


#: an orientation is a gross error only this far [deg] from the probe frame the other rows agree on: against the
#: nominal model a real arm's rows spread with heavy tails, and whole regions of its workspace can sit degrees off
#: (the real UR10: up to two degrees in Series C, a cluster near six in Series D, their positions sound), which the
#: statistical bound alone cut into; a probe frame a tenth of a turn off is no such model error
ORIENTATION_GROSS_DEG = 10.0


def _screen_orientation(res: RobustResult, model: MeasurementModel, m, pred: Tensor, alpha: float, gross: float):
    """Find the kept rows whose measured orientation (rx, ry, rz) is a gross error, as the positions' screening does
    (a row degrees off among rows within a fraction of one would otherwise pull the fit), and list them in
    ``res.orientation_dropped``: their positions passed their own test, so the row stays and only its orientation is
    left out (a tracker whose orientation frame slipped for part of a series measured the positions well). Each row's
    probe frame in the flange frame (:func:`_probe_frames`) against their robust centre: ``T_i = |log(R_c^T R_i)|^2 /
    sigma_i^2``, scaled by ``s0^2 = max(1, median(T_i) / median(chi2_3))`` (the geometry's own orientation errors and
    joint noise make the spread wider than the probe's sigma), gross above the same bound as the positions (``chi2_3``
    at ``1 - alpha / n`` and ``gross^2``) and :data:`ORIENTATION_GROSS_DEG` off. Rows without orientation: nothing."""
    if m.r is None or m.n < 4:
        return
    e = _orientation_offsets(model, m)
    sigma = m.sigma_r.mean(dim=-1) if m.sigma_r is not None else torch.full_like(e[:, 0], SIGMA_ORIENTATION)
    T = (e**2).sum(-1) / sigma.clamp(min=1e-12) ** 2
    s0sq = max(float(T.median()) / _chi2_median(3), 1.0)
    z = T / s0sq
    far = e.norm(dim=-1) > math.radians(ORIENTATION_GROSS_DEG)
    bad = (z > max(chi2_isf(alpha / max(m.n, 1), 3), gross**2)) & far & res.kept
    size = (pred - m.p).norm(dim=-1)
    for i in torch.nonzero(bad).flatten().tolist():
        angle = math.degrees(float(e[i].norm()))
        res.orientation_dropped.append(
            Rejected(
                index=i,
                line=int(m.lines[i]),
                statistic=float(z[i]),
                p_value=chi2_sf(float(z[i]), 3),
                size_mm=float(size[i]) * 1e3,
                hint=f"the orientation (rx, ry, rz) is {angle:.3g} deg off the probe frame the other rows agree on; "
                "its position is used",
            )
        )


def _orientation_offsets(model: MeasurementModel, m) -> Tensor:
    """Each row's probe frame in the flange frame against their robust centre, as a rotation vector ``(N, 3)``
    [rad]; refuses orientations that do not turn with the robot at all (:data:`MAX_ORIENTATION_SPREAD_DEG`)."""
    R = _probe_frames(model, m)
    probe = (
        m.probe if model.robot.probes and m.probe is not None else torch.zeros(m.n, dtype=torch.long, device=m.q.device)
    )
    e = torch.empty(m.n, 3, dtype=R.dtype, device=R.device)
    for k in torch.unique(probe).tolist():  # each reflector has a frame of its own in the flange frame
        rows = torch.nonzero(probe == k).flatten()
        e[rows] = so3_log(_common_frame(R[rows]).transpose(-1, -2) @ R[rows])
    spread = math.degrees(float(e.norm(dim=-1).median()))
    if spread > MAX_ORIENTATION_SPREAD_DEG:
        raise MeasurementFileError(
            m.source or "the measurements",
            f"the orientations (rx, ry, rz) do not turn with the robot: the probe frame they give in the flange frame "
            f"differs between rows by a median {spread:.3g} deg (a rigid probe: within a fraction of a degree)",
            column="rx",
            hint="rx, ry, rz must be the probe frame's orientation in the tracker frame as a rotation vector [rad]; "
            "leave the columns out if the instrument did not measure it",
        )
    return e


def screen_geometric(
    model: MeasurementModel,
    train,
    hold,
    opts: FitOptions,
    *,
    trajectory: bool = False,
    alpha: float = DEFAULT_ALPHA,
    gross: float = GROSS_FACTOR,
) -> Screening:
    """Robust geometric fit on the training poses, then the training and held-out poses tested.

    1. Robust start: tracker pose and lever arm with the nominal geometry
       (:func:`~torchcal.estimate.rigid.robust_instrument_and_tool`); its weights start step 2.
    2. The identifiable geometric errors, tracker pose and lever arm (the same identifiability analysis
       and geometric prior as the calibration's geometric stage) by :func:`robust_least_squares`.
    3. Held-out poses: ``T_i = e_i^T (Sigma_i + J_i Q J_i^T)^-1 e_i / s0^2`` against the same model, with
       ``s0^2 = max(1, median(T_i) / median(chi2_3))`` over the held-out poses, at the family-wise level
       ``alpha`` over the held-out poses and with the same bound ``gross``.

    Args:
        model: the calibration's measurement model before any fit (it is copied, not changed).
        train, hold: :class:`~torchcal.data.Measurements` of the training and held-out poses.
        opts: the settings the calibration's fits read (:class:`~torchcal.estimate.fit.FitOptions`): the
            stochastic model, the identifiability tolerance, the geometric prior and the LM's limits.

    Returns:
        :class:`Screening`; its ``training.kept`` and ``holdout.kept`` select the rows to use.
    """
    model = copy.deepcopy(model)
    w0 = _robust_start(model, train)
    ctx = Context.from_measurements(train, trajectory=trajectory)
    W = whitening(model, ctx, train.sigma, opts.sigma_tracker, opts.sigma_joint)
    free, prior = _identifiable_geometry(model, ctx, train, W, opts)
    fun = residual_function(model, free, ctx, train.p, W, prior)
    res = robust_least_squares(
        fun,
        free.vector(),
        train.n,
        names=free.names,
        weights0=w0,
        alpha=alpha,
        max_iter=opts.max_iter,
        stat_tol=opts.stat_tol,
        gross=gross,
    )
    free.assign(res.result.x)
    with torch.no_grad():
        _name_rows(res, train, model(ctx))
        _screen_orientation(res, model, train, model(ctx), alpha, gross)
    hres = _test_holdout(model, free, hold, res.result.cofactor, opts, trajectory, alpha, gross)
    method = (
        "robust start (Tukey-reweighted rigid fit), M-estimation (Huber, then Tukey's biweight, robust scale "
        "from the median) of the geometric model, then Baarda's data snooping one pose at a time; held-out "
        "poses tested against the robust geometric model"
    ) + (
        "; orientations (rx, ry, rz) tested against the probe frame the rows agree on, a gross one left out and its "
        "row's position kept"
        if train.r is not None
        else ""
    )
    return Screening(
        training=res,
        holdout=hres,
        model=model,
        method=method,
        gross=gross,
        free=free.names,
        orientations_tested=train.r is not None,
    )


def _robust_start(model: MeasurementModel, train) -> Tensor:
    """Step 1 of :func:`screen_geometric`: set ``model``'s tracker pose and lever arm from a robust rigid fit with
    the nominal geometry; returns that fit's row weights. With several stations or probes, each pair of a station
    and a probe is one rigid body of its own (its rows: one pose and one lever arm), fitted robustly alone; the poses
    of every station and the lever arms of every probe are then placed together on the rows those fits kept."""
    robot = model.robot
    if not (robot.stations or robot.probes):
        with torch.no_grad():
            T, lever, _, w0 = robust_instrument_and_tool(robot(train.q), train.p)
            robot.instrument.set_matrix(T)
            robot.tool.nominal.copy_(lever)
        return w0
    from torchcal.estimate.fit import place_stations_and_probes

    n = train.n
    zeros = torch.zeros(n, dtype=torch.long, device=train.q.device)
    st = train.station if train.station is not None and robot.stations else zeros
    pr = train.probe if train.probe is not None and robot.probes else zeros
    w0 = torch.ones(n, dtype=train.p.dtype, device=train.p.device)
    with torch.no_grad():
        Tf = robot(train.q)
        for key in torch.unique(st * (int(pr.max()) + 1) + pr).tolist():
            rows = torch.nonzero(st * (int(pr.max()) + 1) + pr == key).flatten()
            if len(rows) < MIN_GROUP_ROWS:  # too few to tell a gross row from a good one: they weigh as given
                continue
            w0[rows] = robust_instrument_and_tool(Tf[rows], train.p[rows])[3]
        kept = torch.nonzero(w0 > 0).flatten()
        place_stations_and_probes(robot, train.q[kept], train.p[kept], st[kept], pr[kept])
    return w0


def _identifiable_geometry(model: MeasurementModel, ctx: Context, train, W: Tensor, opts: FitOptions):
    """The free parameters of step 2 of :func:`screen_geometric` (the identifiable geometric errors, tracker pose and
    lever arm, as the calibration's geometric stage) and their prior sigmas (None without a geometric prior)."""
    groups = ("geometry", "instrument", "tool")
    sel, labels = selection(model, groups)
    free = FreeParameters(model, sel, labels)
    fun = residual_function(model, free, ctx, train.p, W)
    J = jacobian_of(fun)(free.vector())  # the Jacobian does not depend on the measured points
    ida = analyse(J, free.names, preference_order(free.names), tol=opts.rank_tol)
    sel, labels = selection(model, groups, dict(zip(free.names, ida.free.tolist())))
    free = FreeParameters(model, sel, labels)
    prior = None
    if opts.prior_length is not None and opts.prior_angle is not None:
        units = {i.name: i.unit for i in model.robot.parameter_info() if i.group == "geometry"}
        prior = prior_sigmas(free, units, opts.prior_length, opts.prior_angle)
    return free, prior


def _test_holdout(model, free, hold, Q: Tensor, opts: FitOptions, trajectory: bool, alpha: float, gross: float):
    """Step 3 of :func:`screen_geometric`: the held-out poses against the robust model, the parameters' cofactor
    ``Q`` included."""
    hctx = Context.from_measurements(hold, trajectory=trajectory)
    Wh = whitening(model, hctx, hold.sigma, opts.sigma_tracker, opts.sigma_joint)
    hfun = residual_function(model, free, hctx, hold.p, Wh)
    x = free.vector()
    Jh = jacobian_of(hfun)(x).reshape(hold.n, 3, -1)
    with torch.no_grad():
        pred = model(hctx)
        e = Wh @ (pred - hold.p).unsqueeze(-1)
    S = torch.eye(3, dtype=F64, device=Jh.device) + Jh @ Q @ Jh.transpose(1, 2)
    Th = (torch.linalg.solve(S, e) * e).sum((1, 2))
    s0sq = max(float(Th.median()) / _chi2_median(3), 1.0)
    thr = max(chi2_isf(alpha / max(hold.n, 1), 3), gross**2)
    zh = Th / s0sq
    hres = RobustResult(
        kept=zh <= thr,
        statistic=zh,
        threshold=thr,
        alpha=alpha,
        sigma0_sq=s0sq,
        iterations=0,
        status="converged",
        weights=(zh <= thr).to(F64),
    )
    _name_rows(hres, hold, pred)
    with torch.no_grad():
        _screen_orientation(hres, model, hold, pred, alpha, gross)
    return hres
