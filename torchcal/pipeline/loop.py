"""Closing the loop: from the residuals of a fit to the effects the model lacks.

After the geometric fit, repeat:

1. score every remaining candidate (:mod:`torchcal.diagnose.candidates`) at the current fit of
   the training poses (:func:`~torchcal.diagnose.score.score_candidates`: score test, Bonferroni
   over the candidates, identifiability against the current parameters), and localise the training
   residual (:mod:`torchcal.diagnose.tracing`: a penalised smooth per variable, Bonferroni over the
   variables); at the strongest significant variable whose BIC-chosen form has an effect class, that
   form is an open candidate (in that pass it replaces the menu's fixed form of the same name);
2. refit the whole model (geometry, instrument, lever arm, the effects accepted so far and the
   candidate, jointly) on 80 % of the training poses with the open candidate and with the significant
   menu candidates in order of evidence (smallest p first) until one of them passes; a candidate passes
   when the other 20 % (the validation poses, never used to fit) confirm the gain: lower RMSE and a
   one-sided paired test (:func:`~torchcal.stats.paired_test`) below ``alpha_val``; an open joint form must
   besides hold at the edges of its joint's range: refitted without the outer 10 % of the fitting poses on each
   side, it must not predict them significantly worse than the model without it (:func:`_validate_edge`).
   Each candidate is screened first by one Gauss-Newton step from the base fit instead of the refit (the base is at
   its optimum, so the step is nearly the refit's; :func:`_screen`, :func:`_screen_edge`): where the step is
   trusted (the cost fell as its linearisation predicts) and fails a check by a wide margin (a validation p ten
   times the level or no lower RMSE, an edge p a tenth of it, a joint function too large by half again, a normal
   matrix singular at the rounding level), the candidate is rejected on the step's numbers, said so in its
   record (``validation.screened``); every other candidate, and so every accepted one, is refitted as above;
3. of those that passed, the one with the lowest validation RMSE (among those the paired test cannot tell
   apart on the validation poses, the lowest BIC of the fit on the fitting poses: the fewer-parameter form
   when two explain the same structure) is refitted jointly on all training poses and becomes a stage of
   the story (the other stays untried); a rejected one is recorded with its evidence and not tried again;

until neither the score tests nor the localisation propose a candidate, or none passes validation. The
global test is reported after every step but does not stop the search: for an alternative with one to
six parameters spread over thousands of observations it has little power, the score test much more.
When the loop ends with the global test failing, ``Diagnosis.unexplained`` lists the significant
variables of the final model's training residual, with their share and evidence
(:func:`~torchcal.diagnose.tracing.unexplained_entries`).
The split into fitting and validation poses is the calibration's own rule applied to the training
poses (a seeded random 20 %, or the last 20 % of a trajectory).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field

import torch

from torchcal import _console
from torchcal import stats as S
from torchcal.data import Measurements
from torchcal.diagnose.candidates import Candidate, candidates
from torchcal.diagnose.score import Score, named_p, score_candidates
from torchcal.diagnose.stations import station_consistency
from torchcal.diagnose.tracing import (
    LocalisationScore,
    OpenCandidate,
    effect_form_params,
    localise_fit,
    open_candidates,
    unexplained_entries,
)
from torchcal.effects import Context, MeasurementModel, joint_function_check
from torchcal.effects.drift import Drift
from torchcal.effects.joint import LUMPED_FORM, MAX_COMPLIANCE, LumpedCompliance, RegionForm, TorqueCompliance
from torchcal.errors import EstimationError
from torchcal.estimate.fit import GEOMETRIC_GROUPS, effect_parameters, errors, gauss_newton_step, solve
from torchcal.estimate.identifiability import MAX_CORRELATION, weak_combinations
from torchcal.estimate.lm import SINGULAR_EIGENVALUE
from torchcal.pipeline.effect_holds import hold_trades
from torchcal.pipeline.holdout import GUARD_MIN_POSES
from torchcal.pipeline.records import Cause, Decision, Diagnosis, EffectRecord, Rejection
from torchcal.pipeline.state import CalibrationRun, StageResult, StageWork
from torchcal.stats import at_edges

Tensor = torch.Tensor
GROUPS = GEOMETRIC_GROUPS
DESCRIPTORS = ("source", "harmonics", "variable", "target", "reference", "payload_kg")  # fixed settings of effects


def close_loop(
    run: CalibrationRun, *, max_effects: int = 8, max_tries: int = 4, open_forms: bool = True
) -> StageResult:
    """The effects the training data demand, added to the run's model (module docstring).

    Each accepted effect becomes a checkpoint of the story, with its :class:`EffectRecord`; each candidate that
    validation does not confirm, a :class:`Rejection`; the search itself, the result's ``diagnosis``.

    Args:
        run: a run whose last fit is the geometric one; only its training poses are seen here.
        max_effects: at most this many effects are added.
        max_tries: significant candidates validated per round before the loop gives up.
        open_forms: also localise the residual each round and propose the form chosen there
            (:mod:`torchcal.diagnose.tracing`); at the end, report what is left (``Diagnosis.unexplained``).
    """
    work = StageWork(run, "closed loop")
    search = _Search.start(run, work, open_forms)
    if not search.cands:
        search.diag.stop = "no candidate effects for these data"
        return work.result()
    for rnd in range(1, max_effects + 1):
        scores, significant, opens = search.propose(rnd)
        if not significant and not opens:
            break
        passed = search.validate_round(rnd, significant, opens, max_tries)
        if not passed:
            search.diag.stop = f"round {rnd}: no significant candidate passed validation"
            break
        if not search.accept_best(passed):
            search.diag.stop = f"round {rnd}: no confirmed candidate could be refitted on all training poses"
            break
    else:
        search.diag.stop = f"reached the limit of {max_effects} effects"
        for loc in localise_fit(work.model, search.ctx, run.train.p, work.fits[-1])[0] if open_forms else []:
            search.open_notes.setdefault(loc.name, f"the loop reached its limit of {max_effects} effects")
    search.diag.trades = _hold_trades(work, effect_trades(work.model, work.fits[-1]))
    final = work.fits[-1]
    _stations(search, final)
    if open_forms and not final.global_test.get("passed", True):
        # the final search round localised this same fit where no hold refitted it since: its localisation is reused
        last = search.localised
        search.diag.unexplained = unexplained_entries(
            work.model,
            search.ctx,
            run.train.p,
            final,
            run.options.levels.score,
            search.open_notes,
            localised=last[1:] if last is not None and last[0] is final else None,
        )
    return work.result()


@dataclass
class _Search:
    """The closed loop's search as it stands: the candidates, the fitting and validation poses, the base model the
    next candidate is judged against, and what was tried, accepted and noted."""

    run: CalibrationRun
    work: StageWork
    ctx: Context  # the training poses' context
    cands: list  # the menu of candidate effects
    fit_part: Measurements  # the training poses each candidate is fitted on
    val_part: Measurements  # the training poses it is judged on (never fitted)
    diag: Diagnosis
    open_forms: bool
    base: MeasurementModel | None = None  # the model with the effects accepted so far, fitted on ``fit_part``
    e_base: Tensor | None = None  # its validation errors
    tried: set[str] = field(default_factory=set)  # menu candidates tried
    tried_open: set[str] = field(default_factory=set)  # open candidates tried (by effect name)
    accepted_names: set[str] = field(default_factory=set)
    open_notes: dict[str, str] = field(default_factory=dict)  # variable -> why no open effect came from it
    # joint -> the current base refitted without that joint's edge poses: its errors there (None: the refit
    # failed); emptied when a new effect makes a new base
    edge_bases: dict[int, Tensor | None] = field(default_factory=dict)
    # joint -> the current base stepped (one Gauss-Newton step) without that joint's edge poses: its errors there, for
    # the screen (:func:`_screen_edge`); emptied with ``edge_bases``
    edge_steps: dict[int, Tensor | None] = field(default_factory=dict)
    localised: tuple | None = None  # (fit, localisations, workspace) of the latest localisation

    @classmethod
    def start(cls, run: CalibrationRun, work: StageWork, open_forms: bool) -> _Search:
        """The search before its first round: the candidates, the split, the base fitted on the fitting poses."""
        train, opts = run.train, run.options
        ctx = Context.from_measurements(train, trajectory=run.trajectory)
        cands, skipped = candidates(work.model.robot, ctx)
        fi, va = S.split(
            train.n,
            S.validation_count(train.n),
            seed=opts.seed + S.Stream.VALIDATION,
            last=run.trajectory,
            q=train.q,
            group_tol=opts.split.group_tol,
        )
        # the levels: of the score tests (family-wise, Bonferroni over the candidates) and of the paired validation
        diag = Diagnosis(opts.levels.score, opts.levels.validation, len(fi), len(va), list(cands), skipped)
        work.diagnosis = diag
        search = cls(run, work, ctx, cands, train.subset(fi), train.subset(va), diag, open_forms)
        if cands:
            search.base = copy.deepcopy(work.model)
            search.fit_on(search.base, search.fit_part, "validation baseline", covariance=False)
            search.e_base = errors(search.base, search.val_part, run.trajectory)
        return search

    def fit_on(self, m: MeasurementModel, data: Measurements, stage: str, *, covariance: bool = True):
        """``m`` refitted on ``data`` (the geometry and the named effects); ``covariance`` False for a refit judged by
        its solution alone (the validations': no Jacobian at the solution, :func:`~torchcal.estimate.fit.solve`)."""
        opts = self.run.options
        return solve(
            m,
            data,
            GROUPS,
            opts.fit,
            stage,
            trajectory=self.run.trajectory,
            effects=True,
            identifiability=self.run.identifiability,
            covariance=covariance,
        )

    def step_on(self, m: MeasurementModel, data: Measurements):
        """``m`` moved by one Gauss-Newton step of :meth:`fit_on`'s problem on ``data``
        (:func:`~torchcal.estimate.fit.gauss_newton_step`); None where it cannot be taken."""
        return gauss_newton_step(
            m,
            data,
            GROUPS,
            self.run.options.fit,
            trajectory=self.run.trajectory,
            identifiability=self.run.identifiability,
        )

    def propose(self, rnd: int) -> tuple[list, list, list]:
        """Round ``rnd``'s scores of the menu candidates left, the significant ones, and the open candidates of the
        localisation; recorded in the diagnosis, with the reason to stop where none is significant."""
        model, fit, train = self.work.model, self.work.fits[-1], self.run.train
        alpha = self.diag.alpha
        remaining = [c for c in self.cands if c.name not in self.tried and c.name not in self.accepted_names]
        scores = (
            score_candidates(
                model,
                fit.result,
                self.ctx,
                train.p,
                fit.whitening,
                cands=remaining,
                tol=self.run.options.fit.rank_tol,
            )
            if remaining
            else []
        )
        locs, ws = localise_fit(model, self.ctx, train.p, fit)
        self.localised = (fit, locs, ws)
        opens, notes = (
            open_candidates(model, locs, ws, alpha, self.tried_open | self.accepted_names)
            if self.open_forms
            else ([], [])
        )
        for n in notes:
            self.open_notes.setdefault(n["variable"], n["reason"])
        self.diag.rounds.append(
            {
                "round": rnd,
                "scores": scores,
                "global_test": fit.global_test,
                "localisation": [loc.to_dict() for loc in locs[:6]],
                "open_candidates": [c.to_dict() for c in opens],
                "open_notes": notes,
            }
        )
        significant = [s for s in scores if s.significant(alpha)]
        if not significant and not opens:
            self.diag.stop = _no_candidate_reason(rnd, scores, locs, alpha)
        return scores, significant, opens

    def validate(self, rnd: int, cand, s) -> _Validation:
        """``cand`` refitted with the base on the fitting poses and judged on the validation poses (an open joint
        form at the edges of its joint's range too); a candidate that fails is recorded as rejected. The screen
        (:func:`_screen`) rejects, without the refit, a candidate whose one-step prediction fails by a wide margin."""
        # said before the screen: the terminal names every candidate's score where it is judged, screened or refitted
        _console.info(
            f"diagnosis round {rnd}: {cand.name} ({named_p(s.to_dict())}): validating on {len(self.val_part.q)} poses"
        )
        v = self.screen(rnd, cand, s) if self.run.identifiability is not None else None
        if v is not None:
            _reject(self.work, self.diag, v)
            if isinstance(cand, OpenCandidate):
                self.open_notes[cand.choice.variable.name] = f"{cand.name} ({cand.choice.form}) rejected: {v.reason}"
            return v
        v = _validate(
            s,
            rnd,
            base=self.base,
            e_base=self.e_base,
            fit_on=self.fit_on,
            fit_part=self.fit_part,
            val_part=self.val_part,
            trajectory=self.run.trajectory,
            alpha_val=self.diag.alpha_validation,
            cand=cand,
            max_size=self.run.options.loop.max_joint_error,
        )
        if v.passed and isinstance(v.trial.effects[-1], RegionForm):
            _validate_edge(
                v,
                self.base,
                self.fit_on,
                self.fit_part,
                trajectory=self.run.trajectory,
                alpha_val=self.diag.alpha_validation,
                cache=self.edge_bases,
            )
        if not v.passed:
            _reject(self.work, self.diag, v)
            if isinstance(cand, OpenCandidate):
                self.open_notes[cand.choice.variable.name] = f"{cand.name} ({cand.choice.form}) rejected: {v.reason}"
        return v

    def screen(self, rnd: int, cand, s) -> _Validation | None:
        """``cand`` judged by one Gauss-Newton step from the base (:func:`_screen`, :func:`_screen_edge`): the rejected
        :class:`_Validation` where the step says it fails by a wide margin, else None (it is refitted)."""
        v = _screen(s, rnd, cand, self)
        if v is None or not v.passed:
            return v
        if isinstance(v.trial.effects[-1], RegionForm):
            v = _screen_edge(v, self)
        return v if v is not None and not v.passed else None

    def validate_round(self, rnd: int, significant: list, opens: list, max_tries: int) -> list[_Validation]:
        """The round's confirmed candidates: the strongest open form, then the significant menu candidates in order
        of evidence until one passes (at most ``max_tries``)."""
        passed: list[_Validation] = []
        for c in opens[:1]:
            self.tried_open.add(c.name)
            v = self.validate(rnd, c, LocalisationScore(c.localisation, c.choice))
            if v.passed:
                passed.append(v)
        # a confirmed open form at a place replaces the menu's fixed form there (same effect name)
        open_names = {v.candidate.name for v in passed}
        menu = [s for s in significant if s.candidate.name not in open_names]
        for s in menu[:max_tries]:
            self.tried.add(s.candidate.name)
            v = self.validate(rnd, s.candidate, s)
            if v.passed:
                passed.append(v)
                break
        return passed

    def accept_best(self, passed: list[_Validation]) -> bool:
        """Accept the candidate chosen on validation (ties by BIC); the others stay untried for the next round.
        One whose refit on all the training poses fails (rank deficient there, at the edge of what the fitting
        poses allowed) is rejected and the next choice among the rest takes its place. False: none could be."""
        accepted = None
        remaining = list(passed)
        while remaining:
            v = _choose(remaining, self.run.trajectory, self.diag.alpha_validation, self.work)
            if _accept(self.work, self.diag, v, self.fit_on, self.run.train):
                accepted = v
                break
            remaining.remove(v)
        if accepted is None:
            return False
        others = [v.candidate.name for v in passed if v is not accepted and not v.rejected]
        _console.info(
            f"diagnosis round {accepted.round}: {accepted.candidate.name} accepted"
            + (f" (the best confirmed; {', '.join(others)} scored again next round)" if others else "")
        )
        for v in passed:
            if v is not accepted and not v.rejected:
                (self.tried_open if isinstance(v.candidate, OpenCandidate) else self.tried).discard(v.candidate.name)
        self.accepted_names.add(accepted.candidate.name)
        self.base, self.e_base = accepted.trial, accepted.errors
        self.edge_bases.clear()
        self.edge_steps.clear()
        return True


def _stations(search: _Search, final) -> None:
    """Whether the stations share the instrument whose errors the loop found (:mod:`torchcal.diagnose.stations`):
    the tests go to the diagnosis, a station that differs to the run's notes."""
    run = search.run
    search.diag.stations = station_consistency(
        search.work.model,
        final.result,
        search.ctx,
        run.train.p,
        final.whitening,
        run.train.station_names,
        alpha=search.diag.alpha,
    )
    for t in search.diag.stations:
        if t["differs"]:
            search.work.note(
                f"instrument: {t['effect']} differs at station {t['station']} (score test chi2 {t['statistic']:.1f} "
                f"on {t['dof']} dof, Bonferroni p = {t['p_bonferroni']:.2g}): the stations may not share one "
                "instrument; a file per instrument calibrates each apart"
            )


def _hold_trades(work: StageWork, trades: list[dict]) -> list[dict]:
    """Hold the effect members of the trades with the geometry at zero and refit (:mod:`torchcal.pipeline.
    effect_holds`); the last checkpoint and the effects' records then show the model so held. Each trade gets
    ``held`` (the elements held, empty where it is only named) and its note, which the run's notes carry."""
    run = work.run
    fit, names = hold_trades(
        work.model,
        run.train,
        run.identifiability,
        trades,
        run.options.fit,
        trajectory=run.trajectory,
        fit=work.fits[-1],
    )
    if fit is not None:
        work.fits.append(fit)
        name = work.stages.pop().name
        after = work.add_stage(name)
        labels = [e.label() for e in work.model.effects]
        for i, r in enumerate(work.effects):
            if r.label not in labels:
                continue
            params = {**r.params, **effect_parameters(work.model, labels.index(r.label), fit)}
            for short, entry in params.items():
                if f"{r.label}.{short}" in names:
                    entry["note"] = "held at zero: the data cannot tell it from the geometry (identifiability)"
            after_mm = after.rmse * 1e3 if r.label == name else r.rmse_after_mm
            work.effects[i] = dataclasses.replace(r, params=params, rmse_after_mm=after_mm)
    for t in trades:
        t["held"] = [n for n in t["effects"] if n in names]
        if t["held"]:
            t["note"] = t["note"].replace(
                "the values along it are the priors' and the start's",
                f"held at the effect's zero ({', '.join(t['held'])}): the geometry keeps what both explain",
            )
        elif t.get("kept"):
            far = ", ".join(f"{n} {z:.1f} sigma" for n, z in t["kept"].items())
            t["note"] = t["note"].replace(
                "the values along it are the priors' and the start's",
                f"kept: the data put it far from zero ({far}), though along that direction it shares with the geometry",
            )
        work.note(t["note"])
    return trades


def effect_trades(model: MeasurementModel, fit, max_correlation: float = MAX_CORRELATION) -> list[dict]:
    """The directions the final fit cannot tell between an effect's parameters and the geometry (or another
    effect's): the weak combinations of its cofactor matrix with an effect parameter among their members
    (:func:`~torchcal.estimate.identifiability.weak_combinations`, the after-fit rule of the geometry applied to
    geometry and effects together: an eigenvalue of the unit-diagonal normal matrix below ``1 - max_correlation``).

    The closed loop admits an effect only where its columns are independent of the current ones (the score test),
    but the geometry is analysed once, before any effect, and an effect admitted later can leave a combination with
    the geometry that only the joint fit shows (a joint's cosine harmonic over a narrow range and its offset, a
    coupling and a ratio of the readings map). Such a direction is named, with its members and the move the data
    hardly see; the values along it are the priors' and the start's, not the data's.

    Returns:
        One dict per combination: ``members``, ``effects`` and ``robot`` (its members by kind), ``correlation``
        (``1 -`` the eigenvalue: a pair's ``|rho|``), ``direction`` (the move, scaled to its first member) and
        ``note`` (the sentence the run's notes carry).
    """
    labels = [e.label() for e in model.effects]
    names = list(fit.free.names)
    if not labels or not names:
        return []
    is_effect = torch.tensor([any(n.startswith(f"{lab}.") for lab in labels) for n in names], device="cpu")
    if not bool(is_effect.any()) or bool(is_effect.all()):
        return []
    try:
        Q = fit.result.cofactor
    except EstimationError as err:
        return [
            {
                "members": [],
                "effects": [],
                "robot": [],
                "correlation": 1.0,
                "direction": "",
                "note": (
                    f"identifiability: the final fit's normal matrix is singular ({err}): some direction of the "
                    "effects and the geometry together is not determined by the data"
                ),
            }
        ]
    out = []
    for c in weak_combinations(names, Q, is_effect, max_correlation):
        eff = [n for n, i in zip(c.names, c.indices) if bool(is_effect[i])]
        rob = [n for n, i in zip(c.names, c.indices) if not bool(is_effect[i])]
        rho = 1.0 - c.eigenvalue
        other = f"from {', '.join(rob)}" if rob else "from each other"
        note = (
            f"identifiability: the data cannot tell {', '.join(eff)} {other} (a combination correlated at "
            f"{rho:.5f}: {c.describe()} hardly changes the fit); the values along it are the priors' and the start's"
        )
        out.append(
            {
                "members": list(c.names),
                "effects": eff,
                "robot": rob,
                "correlation": rho,
                "direction": c.describe(),
                "note": note,
            }
        )
    return out


def _no_candidate_reason(rnd: int, scores: list, locs: list, alpha: float) -> str:
    """Why the loop stops in round ``rnd``: no menu candidate nor localisation significant at ``alpha``."""
    best = (
        f"best {scores[0].candidate.name}: Bonferroni p = {scores[0].p_bonferroni:.2g}"
        if scores
        else "no menu candidate left"
    )
    top = f"; localisation: {locs[0].name}, Bonferroni p = {locs[0].p_bonferroni:.2g}" if locs else ""
    if any(loc.significant(alpha) for loc in locs):
        top += " (significant, but no form with an effect class that was not tried)"
    return f"round {rnd}: no candidate significant ({best} >= {alpha}{top})"


@dataclass
class _Validation:
    """One candidate refitted on the fitting poses and judged on the validation poses."""

    score: Score
    round: int
    candidate: Candidate  # a menu candidate, or an open form (tracing.OpenCandidate)
    base: MeasurementModel  # the model before it, fitted on the fitting poses
    trial: MeasurementModel  # with it
    errors: Tensor  # (n_validation,) m: the trial's validation errors
    validation: dict  # the numbers of the test, for the report
    passed: bool
    reason: str
    bic: float = float("nan")  # BIC of the trial's fit on the fitting poses (n ln(RSS / n) + k ln n, whitened)
    rejected: bool = False  # confirmed on validation, but its refit on all training poses failed
    cause: Cause = Cause.VALIDATION  # why it was rejected, where it was


def _validate(
    s: Score,
    rnd: int,
    *,
    base: MeasurementModel,
    e_base: Tensor,
    fit_on,
    fit_part: Measurements,
    val_part: Measurements,
    trajectory: bool,
    alpha_val: float,
    cand=None,
    max_size: float | None = None,
) -> _Validation:
    """Refit ``base`` with ``cand`` (default: the candidate of ``s``) on the fitting poses; compare on the
    validation poses."""
    cand = cand if cand is not None else s.candidate
    trial = copy.deepcopy(base)
    trial.add(_made(cand, fit_part))
    try:
        res = fit_on(trial, fit_part, f"validation {cand.name}", covariance=False).result
    except EstimationError as err:  # a candidate the data cannot fit (rank deficient with it) is rejected, said why
        reason = f"its joint refit on the fitting poses failed ({err})"
        validation = _untested(e_base, None, refit_failed=str(err))
        _console.info(f"diagnosis round {rnd}: {cand.name}: rejected, {reason}")
        return _Validation(s, rnd, cand, base, trial, e_base, validation, False, reason, cause=Cause.REFIT_FAILED)
    e_trial = errors(trial, val_part, trajectory)
    unsure = joint_function_check(trial.effects[-1], fit_part.q, trial.robot, max_size)
    if unsure is not None:  # fits the poses, but explodes just beyond them: never better than without it
        validation = _untested(e_base, e_trial, ill_determined=unsure)
        _console.info(f"diagnosis round {rnd}: {cand.name}: rejected, {unsure}")
        return _Validation(s, rnd, cand, base, trial, e_trial, validation, False, unsure, cause=Cause.ILL_DETERMINED)
    test = S.paired_test(e_base, e_trial, ordered=trajectory)
    r0, r1 = S.rmse(e_base), S.rmse(e_trial)
    validation = {
        "rmse_before_mm": r0 * 1e3,
        "rmse_after_mm": r1 * 1e3,
        "relative_gain": 1.0 - r1 / r0 if r0 > 0 else 0.0,
        **test.to_dict(),
        "rule": f"lower validation RMSE and one-sided paired p < {alpha_val}",
    }
    passed = r1 < r0 and test.p_value < alpha_val
    reason = (
        ""
        if passed
        else (f"validation does not confirm it ({r0 * 1e3:.4f} -> {r1 * 1e3:.4f} mm, p = {test.p_value:.2g})")
    )
    # the variance is estimated (n ln(RSS / n)), not taken as the tracker's: while structure is left, the
    # whitened SS is inflated by s0^2 and a known-variance BIC would let any extra parameter buy it down
    n_obs = max(res.n_obs, 1)
    bic = n_obs * math.log(max(float(res.residuals[:n_obs].square().sum()), 1e-300) / n_obs) + len(res.x) * math.log(
        n_obs
    )
    validation["bic_fit"] = bic
    _console.info(
        f"diagnosis round {rnd}: {cand.name}: {'confirmed' if passed else 'not confirmed'} (validation RMSE "
        f"{r0 * 1e3:.4f} -> {r1 * 1e3:.4f} mm, paired p = {test.p_value:.2g})"
    )
    return _Validation(s, rnd, cand, base, trial, e_trial, validation, passed, reason, bic)


#: the share of a joint's fitting poses on each side of its range that the edge validation holds out
EDGE_SHARE = 0.1


def _edge_split(q: Tensor, joint: int, share: float = EDGE_SHARE) -> tuple[Tensor, Tensor]:
    """The fitting poses' indices in the middle of joint ``joint``'s (1-based) range and at its two edges (the
    outer ``share`` of the poses on each side)."""
    qj = q[:, joint - 1 : joint]
    edge = at_edges(qj, qj, share)
    return torch.nonzero(~edge)[:, 0], torch.nonzero(edge)[:, 0]


def _validate_edge(
    v: _Validation, base, fit_on, fit_part: Measurements, *, trajectory: bool, alpha_val: float, cache: dict
):
    """An open joint form that passed validation on random poses is judged at the edges of its joint's range too:
    refitted without the outer :data:`EDGE_SHARE` of the fitting poses on each side of the range, its continuation
    must not predict them significantly worse than the model without it (one-sided paired test at ``alpha_val``).
    A form that wins in the middle and loses at the edge is rejected with that reason (``v`` updated in place); the
    numbers go to ``v.validation["edge"]``."""
    eff = v.trial.effects[-1]
    mid, edge = _edge_split(fit_part.q, eff.joint)
    # judged on as many poses as a held-out guard asks, and refitted on no fewer
    if len(edge) < GUARD_MIN_POSES or len(mid) < GUARD_MIN_POSES:
        v.validation["edge"] = {"skipped": f"too few poses at the edges of joint {eff.joint} ({len(edge)})"}
        return
    middle, outer = fit_part.subset(mid), fit_part.subset(edge)
    key = eff.joint
    if key not in cache:
        ref = copy.deepcopy(base)
        try:
            fit_on(ref, middle, "edge validation baseline", covariance=False)
            cache[key] = errors(ref, outer, trajectory)
        except EstimationError:
            cache[key] = None
    e_ref = cache[key]
    if e_ref is None:
        v.validation["edge"] = {"skipped": "the baseline's refit without the edge poses failed"}
        return
    trial = copy.deepcopy(base)
    # the form as it continues (its region the whole range of the fitting poses, no fade at the edge poses): the
    # question is whether its shape holds there, and a form faded beyond the middle would lose to geometry that
    # absorbed part of it in any case
    trial.add(_made(v.candidate, fit_part))
    try:
        fit_on(trial, middle, f"edge validation {v.candidate.name}", covariance=False)
    except EstimationError as err:
        v.validation["edge"] = {"skipped": f"its refit without the edge poses failed ({err})"}
        return
    e_edge = errors(trial, outer, trajectory)
    worse = S.paired_test(e_edge, e_ref, ordered=trajectory)  # small p: the model without it is better there
    r0, r1 = S.rmse(e_ref), S.rmse(e_edge)
    v.validation["edge"] = _edge_evidence(eff.joint, len(edge), r0, r1, worse.p_value, alpha_val)
    if r1 > r0 and worse.p_value < alpha_val:
        v.passed, v.cause = False, Cause.EDGE
        v.reason = _edge_reason(eff.joint, len(edge), r0, r1, f"p = {worse.p_value:.2g}")


def _edge_evidence(joint: int, n: int, r0: float, r1: float, p_worse: float, alpha_val: float) -> dict:
    """The edge test's record: ``r0``, ``r1`` the RMSE [m] at the ``n`` edge poses without and with the form."""
    return {
        "n": n,
        "share_per_side": EDGE_SHARE,
        "rmse_without_mm": r0 * 1e3,
        "rmse_with_mm": r1 * 1e3,
        "p_worse": p_worse,
        "rule": f"fitted on the middle of joint {joint}'s range, not worse at its edges (one-sided paired p "
        f">= {alpha_val})",
    }


def _edge_reason(joint: int, n: int, r0: float, r1: float, tail: str) -> str:
    """Why a form fails the edge test (``tail`` ends the parenthesis: its p, and how it was judged)."""
    return (
        f"it wins in the middle and loses at the edge: fitted without the outer {EDGE_SHARE:.0%} of joint "
        f"{joint}'s range on each side, it predicts those {n} poses worse than the model without it "
        f"({r0 * 1e3:.4f} -> {r1 * 1e3:.4f} mm, {tail})"
    )


#: the screen trusts its step where the fitting poses' cost fell by this share of the linearised prediction or more,
#: and by no more than its inverse (:attr:`~torchcal.estimate.fit.Step.agreement`): else the candidate is refitted
SCREEN_AGREEMENT = 0.8
#: the screen rejects a candidate without its refit only by this margin: a validation paired p of ``alpha_val`` times
#: it or more (or no lower RMSE), an edge's p of ``alpha_val`` over it or less, a size of its bound times it or more
SCREEN_MARGIN = 10.0
#: the size margin of an ill-determined joint function (its parameters shrunk by this factor still fail the check)
SCREEN_SIZE_MARGIN = 1.5
SCREENED = "screened: one Gauss-Newton step from the base fit predicts it, not refitted"


def _screen(s, rnd: int, cand, search: _Search) -> _Validation | None:
    """``cand`` added to the base and moved by one Gauss-Newton step on the fitting poses (the base is at its optimum
    there, so the step is nearly the refit's, :func:`_validate`), judged like the refit on the validation poses.

    Returns the :class:`_Validation` of the step (``passed`` as it predicts) where the step is trusted (the cost fell
    as its linearisation predicts, within :data:`SCREEN_AGREEMENT`; a candidate whose form is far from linear over
    the step, or whose normal matrix is singular, is refitted instead: None), its rejection only where it fails by
    the margins of :data:`SCREEN_MARGIN` and :data:`SCREEN_SIZE_MARGIN`; ``passed`` True otherwise.
    """
    trial = copy.deepcopy(search.base)
    trial.add(_made(cand, search.fit_part))
    step = search.step_on(trial, search.fit_part)
    if step is not None and step.singular and step.smallest < SINGULAR_EIGENVALUE / SCREEN_MARGIN:
        return _screened_singular(s, rnd, cand, search, trial, step)
    a = float("nan") if step is None else step.agreement
    if not SCREEN_AGREEMENT <= a <= 1.0 / SCREEN_AGREEMENT:
        return None
    e_base, val, trajectory = search.e_base, search.val_part, search.run.trajectory
    e_trial = errors(trial, val, trajectory)
    base_v = dict(base=search.base, trial=trial, errors=e_trial)
    unsure = joint_function_check(
        trial.effects[-1], search.fit_part.q, trial.robot, search.run.options.loop.max_joint_error
    )
    if unsure is not None:
        shrunk = copy.deepcopy(trial.effects[-1])
        with torch.no_grad():
            for par in shrunk.parameters():
                par.div_(SCREEN_SIZE_MARGIN)
        if (
            joint_function_check(shrunk, search.fit_part.q, trial.robot, search.run.options.loop.max_joint_error)
            is None
        ):
            return None
        validation = {**_untested(e_base, e_trial, ill_determined=unsure), "screened": SCREENED}
        reason = f"{unsure} ({SCREENED})"
        _console.info(f"diagnosis round {rnd}: {cand.name}: rejected, {reason}")
        return _Validation(
            s, rnd, cand, **base_v, validation=validation, passed=False, reason=reason, cause=Cause.ILL_DETERMINED
        )
    alpha_val = search.diag.alpha_validation
    test = S.paired_test(e_base, e_trial, ordered=trajectory)
    r0, r1 = S.rmse(e_base), S.rmse(e_trial)
    if r1 < r0 and test.p_value < SCREEN_MARGIN * alpha_val:
        return _Validation(s, rnd, cand, **base_v, validation={}, passed=True, reason="", bic=step.bic)
    validation = {
        "rmse_before_mm": r0 * 1e3,
        "rmse_after_mm": r1 * 1e3,
        "relative_gain": 1.0 - r1 / r0 if r0 > 0 else 0.0,
        **test.to_dict(),
        "rule": f"lower validation RMSE and one-sided paired p < {alpha_val}",
        "bic_fit": step.bic,
        "screened": SCREENED,
    }
    reason = f"validation does not confirm it ({r0 * 1e3:.4f} -> {r1 * 1e3:.4f} mm, p = {test.p_value:.2g}; {SCREENED})"
    _console.info(f"diagnosis round {rnd}: {cand.name}: not confirmed ({reason})")
    return _Validation(s, rnd, cand, **base_v, validation=validation, passed=False, reason=reason)


def _screened_singular(s, rnd: int, cand, search: _Search, trial: MeasurementModel, step) -> _Validation:
    """``cand`` rejected as a refit that fails: with it the normal matrix at the base fit has a null space at the
    rounding level (its smallest eigenvalue under :data:`~torchcal.estimate.lm.SINGULAR_EIGENVALUE` by the screen's
    margin), which the LM's first iterations would find singular too; the dependence is structural (columns of the
    candidate that the poses cannot tell apart from each other or the geometry), not a matter of where it starts."""
    err = (
        "its normal matrix at the base fit is singular (rank deficient): smallest eigenvalue "
        f"{step.smallest:.1e} of the unit-diagonal matrix{step.hint}"
    )
    reason = f"its joint refit on the fitting poses cannot be solved ({err}; {SCREENED})"
    validation = {**_untested(search.e_base, None, refit_failed=err), "screened": SCREENED}
    _console.info(f"diagnosis round {rnd}: {cand.name}: rejected, {reason}")
    return _Validation(
        s,
        rnd,
        cand,
        search.base,
        trial,
        search.e_base,
        validation,
        False,
        reason,
        cause=Cause.REFIT_FAILED,
    )


def _screen_edge(v: _Validation, search: _Search) -> _Validation | None:
    """:func:`_validate_edge` by one Gauss-Newton step from the base (of it alone and with the form) on the middle of
    the joint's range: ``v`` rejected where the form predicts the edges worse by the margin of :data:`SCREEN_MARGIN`,
    else None (it is refitted). The base's step is cached per joint (``search.edge_steps``)."""
    eff = v.trial.effects[-1]
    fit_part, trajectory = search.fit_part, search.run.trajectory
    mid, edge = _edge_split(fit_part.q, eff.joint)
    if len(edge) < GUARD_MIN_POSES or len(mid) < GUARD_MIN_POSES:
        return None
    middle, outer = fit_part.subset(mid), fit_part.subset(edge)
    if eff.joint not in search.edge_steps:
        ref = copy.deepcopy(search.base)
        step = search.step_on(ref, middle)
        trusted = step is not None and SCREEN_AGREEMENT <= step.agreement <= 1.0 / SCREEN_AGREEMENT
        search.edge_steps[eff.joint] = errors(ref, outer, trajectory) if trusted else None
    e_ref = search.edge_steps[eff.joint]
    if e_ref is None:
        return None
    trial = copy.deepcopy(search.base)
    trial.add(_made(v.candidate, fit_part))
    step = search.step_on(trial, middle)
    if step is None or not SCREEN_AGREEMENT <= step.agreement <= 1.0 / SCREEN_AGREEMENT:
        return None
    e_edge = errors(trial, outer, trajectory)
    alpha_val = search.diag.alpha_validation
    worse = S.paired_test(e_edge, e_ref, ordered=trajectory)
    r0, r1 = S.rmse(e_ref), S.rmse(e_edge)
    if not (r1 > r0 and worse.p_value < alpha_val / SCREEN_MARGIN):
        return None
    r_val0, r_val1 = S.rmse(search.e_base), S.rmse(v.errors)
    test = S.paired_test(search.e_base, v.errors, ordered=trajectory)
    v.validation = {
        "rmse_before_mm": r_val0 * 1e3,
        "rmse_after_mm": r_val1 * 1e3,
        "relative_gain": 1.0 - r_val1 / r_val0 if r_val0 > 0 else 0.0,
        **test.to_dict(),
        "rule": f"lower validation RMSE and one-sided paired p < {alpha_val}",
        "bic_fit": v.bic,
        "screened": SCREENED,
        "edge": _edge_evidence(eff.joint, len(edge), r0, r1, worse.p_value, alpha_val),
    }
    v.passed, v.cause = False, Cause.EDGE
    v.reason = _edge_reason(eff.joint, len(edge), r0, r1, f"p = {worse.p_value:.2g}; {SCREENED}")
    _console.info(f"diagnosis round {v.round}: {v.candidate.name}: rejected, {v.reason}")
    return v


def _made(cand, data: Measurements):
    """The candidate's effect, knowing where ``data`` put it: an open form the range its joint covers (beyond it, it
    fades), a drift in time the times of the samples (beyond them, it holds)."""
    eff = cand.make()
    if isinstance(eff, RegionForm):
        eff.set_region(data.q)
    if isinstance(eff, Drift) and getattr(data, "t", None) is not None:
        eff.set_region(data.t)
    return eff


def _untested(e_base: Tensor, e_trial: Tensor | None, **why: str) -> dict:
    """The report's validation numbers of a candidate that was not put to the paired test, with ``why``."""
    nan = float("nan")
    after = nan if e_trial is None else S.rmse(e_trial) * 1e3
    return {
        "rmse_before_mm": S.rmse(e_base) * 1e3,
        "rmse_after_mm": after,
        "relative_gain": nan,
        "z": nan,
        "p_value": nan,
        "n": len(e_base),
        **why,
    }


def _choose(passed: list[_Validation], trajectory: bool, alpha_val: float, work: StageWork) -> _Validation:
    """The candidate to accept among those that passed validation: the lowest validation RMSE, unless another
    is not significantly worse on the validation poses (paired one-sided test, ``alpha_val``); among such ties
    the lowest BIC of the fit on the fitting poses wins. Two forms that explain the same structure equally well
    (a compliance and a two-harmonic cyclic error of the same joint) are then told apart by their evidence
    per parameter, so the fewer-parameter physical form is not lost to a more flexible one by validation noise."""
    best = min(passed, key=lambda v: v.validation["rmse_after_mm"])
    tied = [best] + [
        v
        for v in passed
        if v is not best and S.paired_test(v.errors, best.errors, ordered=trajectory).p_value >= alpha_val
    ]
    chosen = min(tied, key=lambda v: v.bic)
    if chosen is not best:
        work.note(
            f"diagnosis: {chosen.candidate.name} preferred to {best.candidate.name} (validation RMSE "
            f"{chosen.validation['rmse_after_mm']:.4f} vs {best.validation['rmse_after_mm']:.4f} mm, not significantly "
            f"different; BIC {chosen.bic:.1f} vs {best.bic:.1f})"
        )
    return chosen


def _reject(work: StageWork, diag: Diagnosis, v: _Validation) -> None:
    """Record a candidate that validation did not confirm."""
    cand = v.candidate
    diag.decisions.append(Decision(v.round, cand, v.score, False, v.reason, v.validation, None, (v.base, v.trial)))
    evidence = {**v.score.to_dict(), "validation": v.validation}
    work.rejections.append(Rejection(cand.kind, cand.joint, evidence, name=cand.name, reason=v.reason, cause=v.cause))
    work.note(f"diagnosis: {cand.name} ({named_p(v.score.to_dict())}) rejected, {v.reason}")


def _accept(work: StageWork, diag: Diagnosis, v: _Validation, fit_on, train: Measurements) -> bool:
    """Add a confirmed candidate to the run's model, refit on all training poses, open its stage and record it.

    Returns False, with the candidate rejected and the model as it was, when the refit fails (the solver writes
    no parameter then).
    """
    model, s, cand = work.model, v.score, v.candidate
    before = copy.deepcopy(model)
    eff = _made(cand, train)
    model.add(eff)
    label = eff.label()
    # warm start: the validation refit has fitted the same model on 80 % of these poses; from there the refit on all
    # of them takes a few iterations instead of repeating the crawl along the flat valleys of real data
    warm = v.trial.state_dict()
    if set(warm) == set(model.state_dict()):
        model.load_state_dict(warm)
    try:
        new_fit = fit_on(model, train, label)
        # the refit on all training poses is judged like the validation refit: determined and of a physical size
        unsure = joint_function_check(eff, train.q, model.robot, work.options.loop.max_joint_error)
        if unsure is not None:
            raise EstimationError(unsure)
    except EstimationError as err:
        del model.effects[len(model.effects) - 1]
        model.load_state_dict(before.state_dict())
        v.passed, v.rejected, v.cause = False, True, Cause.REFIT_FAILED
        v.reason = f"confirmed on validation, but its joint refit on all training poses failed ({err})"
        _reject(work, diag, v)
        return False
    work.fits.append(new_fit)
    st_before = work.stages[-1]
    st_after = work.add_stage(label)
    diag.decisions.append(
        Decision(
            v.round,
            cand,
            s,
            True,
            "significant and confirmed on validation poses",
            v.validation,
            label,
            (before, copy.deepcopy(model)),
        )
    )
    index = len(model.effects) - 1
    params = {
        **effect_parameters(model, index, new_fit),
        **{k: val for k, val in eff.describe().items() if k in DESCRIPTORS},
    }
    if isinstance(cand, OpenCandidate):
        params = effect_form_params(model, index, cand, params)
    if isinstance(eff, LumpedCompliance):  # which compliance this is, and what its modes stand for
        params = {**params, "form": LUMPED_FORM, "moments_over_stiffness": eff.describe()["moments_over_stiffness"]}
    params = _load_form(eff, params)
    work.effects.append(
        EffectRecord(
            cand.kind,
            cand.joint,
            params,
            _evidence(work, diag, v, new_fit),
            name=cand.name,
            label=label,
            rmse_before_mm=st_before.rmse * 1e3,
            rmse_after_mm=st_after.rmse * 1e3,
        )
    )
    work.note(
        f"diagnosis: {cand.name} added ({named_p(s.to_dict())}, chi2 {s.statistic:.1f} on {s.k:.3g} dof; "
        f"validation {v.validation['rmse_before_mm']:.4f} -> "
        f"{v.validation['rmse_after_mm']:.4f} mm, p = {v.validation['p_value']:.2g})"
    )
    return True


#: an encoder order whose score statistic lies within this of the accepted order's is one the data hardly tell from
#: it: 2 ln 20, a likelihood ratio under 20 between two forms of as many parameters
ALIKE_CHI2 = 2.0 * math.log(20.0)


def _evidence(work: StageWork, diag: Diagnosis, v: _Validation, new_fit) -> dict:
    """An accepted candidate's evidence for its record: its score, round, validation and the global test after it; an
    encoder harmonic's orders the data hardly tell from it (``alike``, also noted)."""
    cand = v.candidate
    alike = _alike_orders(cand, diag)
    if alike:
        work.note(
            f"diagnosis: {cand.name}'s order is a guess among {', '.join([cand.name, *alike])}: their score tests lie "
            f"within chi2 {ALIKE_CHI2:g} of each other (a likelihood ratio under 20; over the span of the angle the "
            "data see, these orders hardly differ)"
        )
    return {
        **v.score.to_dict(),
        "round": v.round,
        "validation": v.validation,
        "global_test_after": new_fit.global_test,
        **({"alike": alike} if alike else {}),
    }


def _alike_orders(cand, diag: Diagnosis) -> list[str]:
    """The other orders of an accepted encoder harmonic whose score test in its round came within :data:`ALIKE_CHI2`
    of its own (empty for any other candidate): over a narrow span of the angle neighbouring orders are nearly the
    same function, and the name's order is then the data's best guess among them."""
    if getattr(cand, "kind", None) != "instrument" or getattr(cand, "order", None) is None or not diag.rounds:
        return []
    scores = diag.rounds[-1]["scores"]
    own = next((x.statistic for x in scores if x.candidate.name == cand.name), None)
    if own is None:
        return []
    return [
        x.candidate.name
        for x in scores
        if x.candidate.name != cand.name
        and getattr(x.candidate, "order", None) is not None
        and x.candidate.variable == cand.variable
        and x.identifiable
        and own - x.statistic < ALIKE_CHI2
    ]


def _load_form(eff, params: dict) -> dict:
    """A load-driven compliance's form and the unit of its compliance ``k`` [rad/(N m)] in its report entry."""
    if not (isinstance(eff, TorqueCompliance) or getattr(eff, "load", False)):
        return params
    out = {**params, "form": eff.describe()["form"]}
    if isinstance(out.get("k"), dict):
        out["k"] = {**out["k"], "unit": "rad/(N m)", "bound": f"0 < k <= {MAX_COMPLIANCE:g} rad/(N m)"}
    return out
