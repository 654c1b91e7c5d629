"""Beyond the calibrated region, the model that travels: which of a run's models predicts a row that lies
outside the joint ranges its training rows covered.

A calibration fits its parameters where its rows were; beyond them each of its models extrapolates in its own way,
and a richer model is not the better there (a kinematic geometry that took up a compliance inside a narrow region
carries it wrongly everywhere else). The candidates, by the names of ``predict``'s ``model`` column:

* ``full``: the run's model, its learned corrections and open joint forms fading to what is left beyond the region;
* ``geometric``: the run's kinematic calibration (a run with effects keeps it beside its model);
* ``physical``: the run's model without the parts that fade (its geometry and named physical effects);
* ``nominal``: the nominal geometry with the fitted instrument pose and lever arm (the run's first stage), whose
  doubt is the geometry's tolerance prior: what not calibrating the robot gives.

The evidence is rows beyond a region that no fit of the candidate saw: the run's held-out rows that lie outside the
training rows' joint ranges (a trajectory's continuation) where there are at least :data:`MIN_EVIDENCE` of them (the
candidates as fitted); else the training rows left out region by region (:func:`folds`: a trajectory's last samples,
or the rows furthest along each joint that moved most), each candidate refitted without them to first order
(:func:`_left_out_errors`). The candidate with the smallest RMSE there predicts every row beyond the region (a richer
one must beat a simpler one by more than :data:`TIE`: the nominal robot is the one a calibration must beat). Where
there is no such evidence the run chooses none and keeps the rule that needs none
(:data:`torchcal.use.rundir.SWITCH_RATIO`). Each candidate's predictive sigma is its own
(:class:`~torchcal.estimate.trust.Trust` measured on the held-out rows), so the sigma of a row beyond the region is the
chosen model's; the run's own model's covariance there is bounded by the tolerance priors (:func:`bounded`).

What the evidence cannot say: no training row tells how a model extrapolates along a joint that did not move. There
the tolerance priors hold the geometry near nominal and bound its sigma.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from torchcal._method import CANDIDATES  # noqa: F401 (predict's model column names them)
from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.covariance import ParameterCovariance, tolerance_bounded
from torchcal.estimate.fit import fit_covariance, prior_scales, selection
from torchcal.estimate.problem import FreeParameters, prior_sigmas
from torchcal.estimate.trust import without_fading
from torchcal.pipeline.records import StageName
from torchcal.pipeline.state import CalibrationRun

#: the fewest held-out rows beyond the region a choice is made on
MIN_EVIDENCE = 10
#: a richer candidate replaces a simpler one only where its RMSE on the evidence is below this share of that one's:
#: on a few dozen rows a smaller gap is the rows' noise, and the simpler model is the one that errs least far out
TIE = 0.99
#: the order in which the candidates are preferred at a tie (simplest first)
SIMPLEST_FIRST = ("nominal", "geometric", "physical", "full")


@dataclass(frozen=True)
class Choice:
    """What predicts the rows beyond the region, and on what evidence.

    Attributes:
        model: the chosen candidate's name (one of :data:`CANDIDATES`), None where the run had too few held-out rows
            beyond its region to choose on.
        n: the held-out rows beyond the region the candidates were compared on.
        rmse_mm: each candidate's RMSE of the 3-D error on those rows [mm].
        max_extrapolation: the largest extrapolation among them [rad or m]: how far the evidence reaches.
        evidence: which rows: ``held-out rows beyond the region`` or ``training rows left out region by region``.
    """

    model: str | None
    n: int
    rmse_mm: dict[str, float]
    max_extrapolation: float
    evidence: str = "none"

    def to_dict(self) -> dict:
        """model.json's and report.json's ``beyond`` entry."""
        return {
            "model": self.model,
            "n_evidence": self.n,
            "rmse_mm": dict(self.rmse_mm),
            "max_extrapolation": self.max_extrapolation,
            "evidence": self.evidence,
            "rule": "the candidate with the smallest RMSE on the held-out rows beyond the region (a simpler one at "
            f"a tie within {100 * (1 - TIE):.0f} %)"
            if self.model is not None
            else f"fewer than {MIN_EVIDENCE} rows beyond the region to compare on: the kinematic calibration where "
            "the model's sigma is more than twice its own",
        }


def nominal_model(run: CalibrationRun) -> MeasurementModel | None:
    """The run's first stage's model (the nominal geometry with the fitted instrument pose and lever arm), on the
    CPU with the run's region (not fading: it has nothing that fades); None where the run has no such stage."""
    stage = next((s for s in run.stages if s.name == StageName.NOMINAL), None)
    if stage is None:
        return None
    out = copy.deepcopy(stage.model).to("cpu")
    out.set_region(run.model.region, fade=False)
    return out


def nominal_covariance(run: CalibrationRun, model: MeasurementModel) -> ParameterCovariance | None:
    """The nominal model's parameter covariance: its instrument pose's and lever arm's from the first stage's fit,
    and the geometry's tolerance prior (the geometric stage's, :meth:`FitSettings.geometric`) on every free geometric
    element: the nominal geometry is as uncertain as the robot's manufacturing. Cross terms are left out, so the
    sigma is the wider (the instrument pose takes up part of a geometric error at the training poses)."""
    settings = run.options.fit.geometric()
    fit = next((f for f in run.fits if f.stage == StageName.NOMINAL), None)
    placed = fit_covariance(fit) if fit is not None else None
    sel, labels = selection(model, ("geometry",))
    free = FreeParameters(model, sel, labels)
    units = {i.name: i.unit for i in model.robot.parameter_info() if i.group == "geometry"}
    ps = prior_sigmas(free, units, settings.prior_length, settings.prior_angle, prior_scales(model, settings))
    ps = torch.where(torch.isfinite(ps), ps, torch.zeros_like(ps)).cpu()
    names = [e.name for e in free.entries]
    index = [[int(i) for i in e.index] for e in free.entries]
    blocks, out_labels = [torch.diag(ps.square())], list(free.names)
    if placed is not None:
        names += placed.names
        index += placed.index
        out_labels += placed.labels
        blocks.append(placed.matrix.to(ps))
    if not len(out_labels):
        return None
    return ParameterCovariance(names, index, out_labels, torch.block_diag(*blocks))


def physical_model(model: MeasurementModel) -> MeasurementModel | None:
    """``model`` without the parts that fade beyond the region (its geometry and named physical effects); None where
    it has none that fade (it is then the full model)."""
    out = without_fading(model)
    return None if len(out.effects) == len(model.effects) else out


def beyond_rows(run: CalibrationRun, model: MeasurementModel) -> tuple[torch.Tensor, torch.Tensor]:
    """The indices into the run's held-out rows that lie beyond the calibrated region, and their extrapolation."""
    hold = run.hold.to("cpu")
    if hold.n == 0:
        return torch.zeros(0, dtype=torch.long, device="cpu"), torch.zeros(0, dtype=torch.float64, device="cpu")
    with torch.no_grad():
        ext = model.extrapolation(hold.q).cpu()
    rows = torch.nonzero(ext > 0).flatten()
    return rows, ext[rows]


def _rmse_mm(e: torch.Tensor) -> float:
    return float(e.norm(dim=1).square().mean().sqrt()) * 1e3


def _simplest_best(rmse: dict[str, float]) -> str:
    """The candidate with the smallest RMSE, a simpler one kept where a richer is not below :data:`TIE` of it."""
    best = None
    for name in SIMPLEST_FIRST:
        if name in rmse and (best is None or rmse[name] < TIE * rmse[best]):
            best = name
    return best


def choose(run: CalibrationRun, candidates: dict[str, MeasurementModel]) -> Choice:
    """Compare ``candidates`` (name -> model, on the CPU) on the held-out rows beyond the region, or where there are
    too few of them on the training rows left out region by region (:func:`left_out`; module docstring)."""
    some = next(iter(candidates.values()))
    rows, ext = beyond_rows(run, some)
    if len(rows) < MIN_EVIDENCE:
        return left_out(run, candidates)
    hold = run.hold.to("cpu").subset(rows)
    ctx = Context.from_measurements(hold, trajectory=run.trajectory)
    with torch.no_grad():
        rmse = {name: _rmse_mm(m(ctx) - hold.p) for name, m in candidates.items()}
    return Choice(_simplest_best(rmse), int(len(rows)), rmse, float(ext.max()), "held-out rows beyond the region")


#: the share of the training rows each leave-one-region-out fold holds out: those furthest along one joint
FOLD_SHARE = 0.15
#: the joints folded along at most (those that moved most, as shares of their limits): each costs two folds of refits
FOLD_JOINTS = 2


def folds(run: CalibrationRun) -> list[torch.Tensor]:
    """Leave-one-region-out folds of the training rows (indices into ``run.train``): for a trajectory its last
    :data:`FOLD_SHARE` of samples (a continuation, as its held-out rows are); for static poses, along each of the
    :data:`FOLD_JOINTS` joints that moved most (as shares of their limits), the rows with the largest and those with
    the smallest readings. Each fold lies beyond the region of the rows left in."""
    train = run.train
    n = train.n
    k = int(FOLD_SHARE * n)
    if k < MIN_EVIDENCE or n - k < 2 * MIN_EVIDENCE:
        return []
    if run.trajectory:
        return [torch.arange(n - k, n)]
    q = train.q.detach().cpu()
    limits = run.robot.limits.detach().cpu()
    span = (limits[:, 1] - limits[:, 0]).clamp(max=2 * torch.pi)
    share = (q.max(dim=0).values - q.min(dim=0).values) / span
    out = []
    for j in torch.argsort(share, descending=True)[:FOLD_JOINTS].tolist():
        order = torch.argsort(q[:, j])
        out += [order[-k:], order[:k]]
    return out


def _fit_setup(run: CalibrationRun, name: str, model: MeasurementModel):
    """How the run fitted candidate ``name``: its groups, settings, free elements and whether its effects are free
    (the nominal one: instrument pose and lever arm; the geometric one: under the tolerance priors, the elements the
    kinematic calibration's identifiability analysis freed; the full one: that geometry with its named effects)."""
    from torchcal.estimate.fit import GEOMETRIC_GROUPS

    geo_fit = next((f for f in run.fits if f.stage == StageName.GEOMETRIC), None)
    ida = None if geo_fit is None else geo_fit.identifiability
    keep = None if ida is None else dict(zip(ida.names, ida.free.tolist()))
    if name == "nominal":
        return ("instrument", "tool"), run.options.fit, None, False
    if name == "geometric" or not model.effects:
        return GEOMETRIC_GROUPS, run.options.fit.geometric(), keep, False
    return GEOMETRIC_GROUPS, run.options.fit, keep, True


def _left_out_errors(run: CalibrationRun, name: str, model: MeasurementModel, parts: list) -> list[torch.Tensor]:
    """The candidate's errors ``(k, 3)`` [m] on each fold of ``parts``, fitted again without that fold to first
    order: one Gauss-Newton step from its fitted values over the rows left in, with its priors (the fit is at its
    optimum on all rows; leaving a share out moves it a little, along a model nearly linear in its corrections)."""
    from torchcal.estimate.fit import _priors
    from torchcal.estimate.problem import jacobian_of, residual_function, whitening

    groups, settings, keep, effects = _fit_setup(run, name, model)
    train = run.train.to("cpu")
    ctx = Context.from_measurements(train, trajectory=run.trajectory)
    sel, labels = selection(model, groups, keep, effects=effects)
    free = FreeParameters(model, sel, labels)
    if not len(free):
        with torch.no_grad():
            e = model(ctx) - train.p
        return [e[h] for h in parts]
    W = whitening(model, ctx, train.sigma, settings.sigma_tracker, settings.sigma_joint)
    fun = residual_function(model, free, ctx, train.p, W, _priors(model, free, settings, groups))
    x0 = free.vector()
    with torch.no_grad():
        r0 = fun(x0)
    J = jacobian_of(fun)(x0).detach()
    out = []
    for held in parts:
        rows = torch.ones(len(r0), dtype=torch.bool, device=r0.device)
        rows[(3 * held[:, None] + torch.arange(3, device=held.device)).flatten()] = (
            False  # the fold's pose rows; the priors stay
        )
        dx = torch.linalg.lstsq(J[rows], -r0[rows].unsqueeze(-1), driver="gelsd").solution.squeeze(-1)
        m = copy.deepcopy(model)
        FreeParameters(m, sel, labels).assign(x0 + dx)
        sub = train.subset(held)
        with torch.no_grad():
            out.append(m(Context.from_measurements(sub, trajectory=run.trajectory)) - sub.p)
    return out


def left_out(run: CalibrationRun, candidates: dict[str, MeasurementModel]) -> Choice:
    """Compare the candidates on the training rows left out region by region (:func:`folds`), each refitted on the
    rest (:func:`_left_out_errors`); the full model stands for itself and for the physical one (its learned parts
    fade beyond the region to the geometry and named effects refitted here)."""
    tested = {n: m for n, m in candidates.items() if n != "physical"}
    if "physical" in candidates:
        tested["full"] = candidates["physical"]
    if not tested["full"].effects:
        # refitted without effects the full model is the kinematic calibration refitted: the two cannot be told
        # apart here, and the full one keeps what fades near the region (on the real UR10's q2 split, Series C, the
        # kinematic calibration beyond the region: 0.558 mm, the full model: 0.463)
        tested.pop("geometric", None)
    parts = folds(run)
    if not parts or len(tested) < 2:
        return Choice(None, 0, {}, 0.0)
    errs = {n: _left_out_errors(run, n, m.to("cpu"), parts) for n, m in tested.items()}
    train = run.train.to("cpu")
    reach = 0.0
    for held in parts:  # how far each fold lies beyond the rows left in
        keep = torch.ones(train.n, dtype=torch.bool, device=train.q.device)
        keep[held] = False
        lo, hi = train.q[keep].min(dim=0).values, train.q[keep].max(dim=0).values
        q = train.q[held]
        reach = max(reach, float(torch.maximum(lo - q, q - hi).clamp(min=0).max()))
    rmse = {n: _rmse_mm(torch.cat(e)) for n, e in errs.items()}
    n = sum(len(h) for h in parts)
    return Choice(_simplest_best(rmse), n, rmse, reach, "training rows left out region by region")


def bounded(
    cov: ParameterCovariance | None, model: MeasurementModel, run: CalibrationRun
) -> ParameterCovariance | None:
    """``cov`` with the geometry's tolerance prior (:meth:`FitSettings.geometric`) added as information on every
    geometric element it holds with a variance above the prior's: ``C - C H^T (H C H^T + P)^-1 H C`` (``H`` picks
    those elements, ``P`` their prior variances). The later fits of a run hold what the rows cannot tell at the
    wider prior of a geometric change (1 mm, 0.1 deg), and beyond the region that doubt would be the sigma; a
    robot's geometry is no more uncertain than its manufacturing, so the sigma beyond the region is bounded by the
    priors the kinematic calibration used."""
    settings = run.options.fit.geometric()
    if cov is None or settings.prior_length is None or settings.prior_angle is None:
        return cov
    return tolerance_bounded(cov, model, settings.prior_length, settings.prior_angle)
