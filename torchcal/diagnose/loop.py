"""Closing the loop: from the residuals of a fit to the effects the model lacks.

After the geometric fit, repeat:

1. score every remaining candidate (:mod:`torchcal.diagnose.candidates`) at the current fit of
   the training poses (:func:`~torchcal.diagnose.score.score_candidates`: score test, Bonferroni
   over the candidates, identifiability against the current parameters), and localise the training
   residual (:mod:`torchcal.diagnose.tracing`: a penalised smooth per variable, Bonferroni over the
   variables); at the strongest significant variable whose BIC-chosen form has an effect class, that
   form is an open candidate (it replaces the menu's fixed form of the same name this round);
2. refit the whole model (geometry, instrument, lever arm, the effects accepted so far and the
   candidate, jointly) on 80 % of the training poses with the open candidate and with the significant
   menu candidates in order of evidence (smallest p first) until one of them passes; a candidate passes
   when the other 20 % (the validation poses, never used to fit) confirm the gain: lower RMSE and a
   one-sided paired test (:func:`~torchcal.effects.kernel.paired_improvement`) below ``alpha_val``;
3. of those that passed, the one with the lowest validation RMSE is refitted jointly on all training
   poses and becomes a stage of the story (the other stays untried); a rejected one is recorded with its
   evidence and not tried again;

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
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from torchcal import _console
from torchcal.diagnose.candidates import Candidate, candidates
from torchcal.diagnose.score import Score, score_candidates
from torchcal.diagnose.tracing import (
    LocalisationScore,
    OpenCandidate,
    effect_form_params,
    localise_fit,
    open_candidates,
    unexplained_entries,
)
from torchcal.effects import Context, MeasurementModel
from torchcal.effects.kernel import paired_improvement

Tensor = torch.Tensor
GROUPS = ("geometry", "instrument", "tool")
DESCRIPTORS = ("source", "harmonics", "variable", "target", "reference", "payload_kg")  # fixed settings of effects


@dataclass
class Decision:
    """One candidate that reached validation: accepted or not, with the evidence."""

    round: int
    candidate: Candidate
    score: Score
    accepted: bool
    reason: str
    validation: dict
    stage: str | None = None  # the stage an accepted effect opened
    models: tuple | None = None  # (before, after) models for the plots; after fitted on the training poses

    def to_dict(self) -> dict:
        return {"round": self.round, **self.candidate.to_dict(), "accepted": self.accepted, "reason": self.reason,
                "score": self.score.to_dict(), "validation": self.validation, "stage": self.stage}


@dataclass
class Diagnosis:
    """Everything the loop looked at, for the report."""

    alpha: float
    alpha_validation: float
    n_fit: int
    n_validation: int
    candidates: list[Candidate] = field(default_factory=list)
    skipped: list[dict] = field(default_factory=list)
    rounds: list[dict] = field(default_factory=list)  # per round: scores and the global test before it
    decisions: list[Decision] = field(default_factory=list)
    stop: str = ""
    unexplained: list[dict] = field(default_factory=list)  # tracing.unexplained_entries of the final model

    def to_dict(self) -> dict:
        return {
            "method": "score tests at the current fit (Bonferroni over the candidates), joint refit, "
                      "confirmation on validation poses (paired one-sided test)",
            "alpha": self.alpha, "alpha_validation": self.alpha_validation,
            "n_fit": self.n_fit, "n_validation": self.n_validation,
            "candidates": [c.name for c in self.candidates], "skipped": self.skipped,
            "rounds": [{"round": r["round"], "global_test": r["global_test"],
                        "scores": [s.to_dict() for s in r["scores"]],
                        **{k: r[k] for k in ("localisation", "open_candidates", "open_notes") if k in r}}
                       for r in self.rounds],
            "decisions": [d.to_dict() for d in self.decisions],
            "stop": self.stop,
        }


def paired_test(e_before: Tensor, e_after: Tensor, ordered: bool) -> dict:
    """One-sided paired test that ``e_after`` is smaller (:func:`~torchcal.effects.kernel.paired_improvement`).

    With ``ordered`` samples (a trajectory: neighbours share their error) the differences are
    autocorrelated and the plain test is overconfident; the standard error is then inflated by
    ``sqrt((1 + rho) / (1 - rho))``, the AR(1) variance factor of a mean, with ``rho`` the lag-one
    autocorrelation of the differences (clamped to [0, 0.99]).
    """
    test = paired_improvement(e_before, e_after)
    if not ordered or len(e_before) < 4:
        return test
    d = e_before.square() - e_after.square()
    d = d - d.mean()
    rho = float((d[1:] * d[:-1]).sum() / d.square().sum().clamp(min=1e-300))
    rho = min(max(rho, 0.0), 0.99)
    z = test["z"] / math.sqrt((1 + rho) / (1 - rho))
    return {**test, "z": z, "p_value": 0.5 * math.erfc(z / math.sqrt(2.0)), "lag1_autocorrelation": rho,
            "z_uncorrected": test["z"]}


def _rmse(e: Tensor) -> float:
    return float(e.square().mean().sqrt()) if len(e) else float("nan")


def effect_parameters(model: MeasurementModel, index: int, fit) -> dict:
    """Estimates with standard deviations of the parameters of ``model.effects[index]`` from ``fit``."""
    from torchcal.calibrate import effect_parameter_labels

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
        for name, v in zip(names, values):
            short = pname + name[len(f"{model.effects[index].label()}.{pname}"):]
            i = pos.get(name)
            out[short] = {"value": v, "std": float(std[i]) if i is not None else None,
                          **({} if i is not None else {"note": "held fixed: not identifiable"})}
    return out


def close_loop(run, train, trajectory: bool, record: Callable[[str], None], *, alpha: float = 0.01,
               alpha_val: float = 0.05, max_effects: int = 8, max_tries: int = 3, open_forms: bool = True) -> Diagnosis:
    """Add the effects the training data demand to ``run.model`` (module docstring).

    Args:
        run: a :class:`~torchcal.calibrate.CalibrationRun` whose last fit is the geometric one.
        train: the training measurements (the held-out poses are never seen here).
        record: called with a stage name after each accepted effect (the run's stage recorder).
        alpha: family-wise level of the score tests (Bonferroni over the candidates).
        alpha_val: level of the paired validation test.
        max_effects: at most this many effects are added.
        max_tries: significant candidates validated per round before the loop gives up.
        open_forms: also localise the residual each round and propose the form chosen there
            (:mod:`torchcal.diagnose.tracing`); at the end, report what is left (``Diagnosis.unexplained``).
    """
    from torchcal import calibrate as CAL

    opts, model = run.options, run.model
    ctx = Context.from_measurements(train, trajectory=trajectory)
    cands, skipped = candidates(model.robot, ctx)
    fi, va = CAL.split(train, 0.2, opts.seed + 2, trajectory)
    fit_part, val_part = train.subset(fi), train.subset(va)
    diag = Diagnosis(alpha, alpha_val, len(fi), len(va), list(cands), skipped)
    run.diagnosis = diag
    if not cands:
        diag.stop = "no candidate effects for these data"
        return diag

    ida = next((f.identifiability for f in reversed(run.fits) if f.identifiability is not None), None)

    def fit_on(m: MeasurementModel, data, stage: str):
        return CAL.solve(m, data, GROUPS, opts, stage, trajectory, effects=True, identifiability=ida)

    base = copy.deepcopy(model)
    fit_on(base, fit_part, "validation baseline")
    e_base = CAL.errors(base, val_part, trajectory)
    tried: set[str] = set()  # menu candidates tried
    tried_open: set[str] = set()  # open candidates tried (by effect name)
    accepted_names: set[str] = set()
    open_notes: dict[str, str] = {}  # variable -> why no open effect came from it (for ``unexplained``)

    def validate(rnd, cand, s):
        """Refit ``base`` with ``cand`` on the fitting poses; the validation record and, when confirmed, the trial."""
        _console.info(f"diagnosis round {rnd}: {cand.name} (chi2 {s.statistic:.1f} on {s.k:.3g}, "
                      f"log10 p {s.log10_p:.1f}); validating")
        trial = copy.deepcopy(base)
        trial.add(cand.make())
        fit_on(trial, fit_part, f"validation {cand.name}")
        e_trial = CAL.errors(trial, val_part, trajectory)
        test = paired_test(e_base, e_trial, ordered=trajectory)
        r0, r1 = _rmse(e_base), _rmse(e_trial)
        validation = {"rmse_before_mm": r0 * 1e3, "rmse_after_mm": r1 * 1e3,
                      "relative_gain": 1.0 - r1 / r0 if r0 > 0 else 0.0, "z": test["z"],
                      "p_value": test["p_value"], "n": test["n"],
                      "rule": f"lower validation RMSE and one-sided paired p < {alpha_val}"}
        if r1 < r0 and test["p_value"] < alpha_val:
            return validation, trial, e_trial
        reason = (f"validation does not confirm it ({r0 * 1e3:.4f} -> {r1 * 1e3:.4f} mm, "
                  f"p = {test['p_value']:.2g})")
        diag.decisions.append(Decision(rnd, cand, s, False, reason, validation, None, (base, trial)))
        run.rejected.append({"kind": cand.kind, "joint": cand.joint, "name": cand.name, "reason": reason,
                             "evidence": {**s.to_dict(), "validation": validation}})
        run.notes.append(f"diagnosis: {cand.name} rejected, {reason}")
        if isinstance(cand, OpenCandidate):
            open_notes[cand.choice.variable.name] = f"{cand.name} ({cand.choice.form}) rejected: {reason}"
        return validation, None, None

    for rnd in range(1, max_effects + 1):
        fit = run.fits[-1]
        remaining = [c for c in cands if c.name not in tried and c.name not in accepted_names]
        scores = score_candidates(model, fit.result, ctx, train.p, fit.whitening, remaining,
                                  tol=opts.rank_tol) if remaining else []
        locs, ws = localise_fit(model, ctx, train.p, fit)
        opens, notes = (open_candidates(model, locs, ws, alpha, tried_open | accepted_names)
                        if open_forms else ([], []))
        for n in notes:
            open_notes.setdefault(n["variable"], n["reason"])
        diag.rounds.append({"round": rnd, "scores": scores, "global_test": fit.global_test,
                            "localisation": [loc.to_dict() for loc in locs[:6]],
                            "open_candidates": [c.to_dict() for c in opens], "open_notes": notes})
        significant = [s for s in scores if s.significant(alpha)]
        if not significant and not opens:
            best = (f"best {scores[0].candidate.name}: Bonferroni p = {scores[0].p_bonferroni:.2g}" if scores
                    else "no menu candidate left")
            top = (f"; localisation: {locs[0].name}, Bonferroni p = {locs[0].p_bonferroni:.2g}" if locs else "")
            if any(loc.significant(alpha) for loc in locs):
                top += " (significant, but no form with an effect class that was not tried)"
            diag.stop = f"round {rnd}: no candidate significant ({best} >= {alpha}{top})"
            break
        passed = []  # (validation rmse, score, candidate, trial, e_trial, validation)
        for c in opens[:1]:
            tried_open.add(c.name)
            s = LocalisationScore(c.localisation, c.choice)
            validation, trial, e_trial = validate(rnd, c, s)
            if trial is not None:
                passed.append((validation["rmse_after_mm"], s, c, trial, e_trial, validation))
        # a confirmed open form at a place replaces the menu's fixed form there (same effect name)
        open_names = {x[2].name for x in passed}
        menu = [s for s in significant if s.candidate.name not in open_names]
        for s in menu[:max_tries]:
            tried.add(s.candidate.name)
            validation, trial, e_trial = validate(rnd, s.candidate, s)
            if trial is not None:
                passed.append((validation["rmse_after_mm"], s, s.candidate, trial, e_trial, validation))
                break
        if not passed:
            diag.stop = f"round {rnd}: no significant candidate passed validation"
            break
        # the candidate that validates best; the others stay untried for the next round
        _, s, cand, trial, e_trial, validation = min(passed, key=lambda x: x[0])
        for _, _, other, *_ in passed:
            if other is not cand:
                (tried_open if isinstance(other, OpenCandidate) else tried).discard(other.name)
        before = copy.deepcopy(model)
        eff = cand.make()
        model.add(eff)
        label = eff.label()
        new_fit = fit_on(model, train, label)
        run.fits.append(new_fit)
        record(label)
        accepted_names.add(cand.name)
        base, e_base = trial, e_trial
        diag.decisions.append(Decision(rnd, cand, s, True, "significant and confirmed on validation poses",
                                       validation, label, (before, copy.deepcopy(model))))
        st_before, st_after = run.stages[-2], run.stages[-1]
        index = len(model.effects) - 1
        params = {**effect_parameters(model, index, new_fit),
                  **{k: v for k, v in eff.describe().items() if k in DESCRIPTORS}}
        if isinstance(cand, OpenCandidate):
            params = effect_form_params(model, index, cand, params)
        run.effects_report.append({
            "kind": cand.kind, "joint": cand.joint, "name": cand.name, "label": label, "params": params,
            "evidence": {**s.to_dict(), "round": rnd, "validation": validation,
                         "global_test_after": new_fit.global_test},
            "rmse_before_mm": st_before.rmse * 1e3, "rmse_after_mm": st_after.rmse * 1e3,
        })
        run.notes.append(f"diagnosis: {cand.name} added (score chi2 {s.statistic:.1f} on {s.k:.3g} dof, "
                         f"Bonferroni p = {s.p_bonferroni:.2g}; validation {validation['rmse_before_mm']:.4f} -> "
                         f"{validation['rmse_after_mm']:.4f} mm, p = {validation['p_value']:.2g})")
    else:
        diag.stop = f"reached the limit of {max_effects} effects"
        for loc in (localise_fit(model, ctx, train.p, run.fits[-1])[0] if open_forms else []):
            open_notes.setdefault(loc.name, f"the loop reached its limit of {max_effects} effects")
    final = run.fits[-1]
    if open_forms and not final.global_test.get("passed", True):
        diag.unexplained = unexplained_entries(model, ctx, train.p, final, alpha, open_notes)
    return diag
