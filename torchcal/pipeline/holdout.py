"""The held-out guards and the refit on all samples: what a run may do with the poses it did not fit.

* :func:`guard_stages` (the ``auto`` method): the final model must be better than the kinematic calibration on
  the held-out poses, and not significantly worse at the edges of the joint ranges; otherwise the run steps back.
* :func:`guard_against_geometry` (the ``integrated`` method's filter): the filter refitted on all training samples
  must be better than geometry alone on the held-out samples with any one of their pieces left out.
* :func:`refit_geometry` / :func:`refit_kinematic` (``Options.refit``): the model written fitted again on all
  samples, training and held-out, once chosen; the held-out errors reported stay those of the training fit.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from torchcal import _console
from torchcal import stats as S
from torchcal.data import Measurements
from torchcal.diagnose.tracing import unexplained_entries
from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.fit import GEOMETRIC_GROUPS, Fit, errors, solve
from torchcal.pipeline.records import Cause, Rejection, StageName
from torchcal.pipeline.state import CalibrationRun, Checkpoint, StageResult, StageWork
from torchcal.stats import HOLDOUT_EDGE, at_edges

Tensor = torch.Tensor


def _rmse(e: Tensor) -> float:
    return S.rmse(e)


#: a path's validation or held-out block is cut into this many consecutive pieces, and a filter must beat geometry
#: alone on the block with any one piece left out: one block of a path is a single draw of how a model
#: extrapolates, and a filter that wins it on average by one good stretch can lose on the path's continuation;
#: asking it to win every piece would reject filters that lose one stretch narrowly and win the rest clearly
VALIDATION_PIECES = 4


#: the fewest poses a guard judges a model on, poses that no model compared was fitted on: the held-out poses of
#: :func:`guard_stages` (overall and at the edges), the held-out samples of :func:`guard_against_geometry`, a joint's
#: edge poses in the closed loop's edge validation. The errors of fewer poses are noise about the model, and a step
#: back on them would throw away what the validation poses confirmed
GUARD_MIN_POSES = 10


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


def guard_against_geometry(model: MeasurementModel, geometric: MeasurementModel, hold: Measurements) -> dict:
    """Whether the final ``model`` is better than the kinematic calibration ``geometric`` on the held-out samples
    (the continuation of the path, fitted by neither): a lower RMSE there with any one of its
    :data:`VALIDATION_PIECES` pieces left out, as on validation (no significance asked: validation chose, this only
    refuses a refit that made things worse). Passed, not judged, on fewer than :data:`GUARD_MIN_POSES` held-out
    samples (at least the :data:`VALIDATION_PIECES` pieces it cuts them into)."""
    if hold.n < max(GUARD_MIN_POSES, VALIDATION_PIECES):
        return {"passed": True, "n": hold.n, "rule": "too few held-out samples to judge"}
    e, e_geo = errors(model, hold, True), errors(geometric, hold, True)
    _, left_out = leave_one_piece_out(e, e_geo)
    return {
        "passed": bool(_rmse(e) < _rmse(e_geo) and max(left_out) < 1.0),
        "n": hold.n,
        "rmse_mm": _rmse(e) * 1e3,
        "geometry_rmse_mm": _rmse(e_geo) * 1e3,
        "leave_one_piece_out_ratios": left_out,
        "rule": "lower held-out RMSE than geometry alone with any one of the pieces left out",
    }


def geometry_on_all(run: CalibrationRun | StageWork, model: MeasurementModel, identifiability, stage: str) -> Fit:
    """``model``'s geometry fitted (in place) on all of ``run``'s samples, training and held-out; returns the fit."""
    return solve(
        model,
        run.fitted_and_held_out,
        GEOMETRIC_GROUPS,
        run.options.fit,
        stage,
        trajectory=run.trajectory,
        identifiability=identifiability,
    )


def refit_geometry(work: StageWork, identifiability) -> dict:
    """Fit the work's geometry (the kinematic calibration) again on all samples, training and held-out
    (``Options.refit``), from its fit on the training samples. The fit joins the work's fits (the report's
    parameters and global test are then the refit's); the checkpoints keep the held-out errors of the fit that did
    not see them. Returns the report's evidence."""
    both = work.fitted_and_held_out
    _console.info(f"geometry fitted again on all {both.n} samples (the held-out errors stay the training fit's)")
    fit = geometry_on_all(work, work.model, identifiability, "refit: geometry on all samples")
    work.fits.append(fit)
    work.note(
        f"refit: the model written was fitted again on all {both.n} samples (training and held-out); the held-out "
        f"errors reported are those of the same fit on the {len(work.train_idx)} training samples only"
    )
    return {"n_samples": both.n, "model": "geometry", "status": fit.result.status}


def refit_kinematic(run: CalibrationRun) -> StageResult:
    """The kinematic method's refit on all samples where ``Options.refit`` asks for it (:func:`refit_geometry`)."""
    work = StageWork(run, "refit")
    if not run.options.refits:
        return work.result(model_changed=False)
    refit_geometry(work, run.fits[-1].identifiability)
    return work.result()


@dataclass
class _GuardView:
    """What the guard compares: every stage from the geometric one on, on all held-out poses and on those at the
    edges of the training poses' joint ranges (a stage must not lose there either)."""

    run: CalibrationRun
    geo: Checkpoint  # the geometric stage: the kinematic calibration
    i_geo: int  # its index among the run's stages
    edge: Tensor  # (n_holdout,) bool: the held-out poses at the edges (:func:`at_edges`)

    @classmethod
    def of(cls, run: CalibrationRun) -> _GuardView:
        geo = run.stage(StageName.GEOMETRIC)
        return cls(run, geo, run.stages.index(geo), at_edges(run.train.q, run.data.q[run.holdout_idx]))

    @property
    def n_edge(self) -> int:
        return int(self.edge.sum())

    def edge_worse(self, st) -> bool:
        """Whether stage ``st`` is significantly worse than the geometric one at the edges (judged on enough poses)."""
        if self.n_edge < GUARD_MIN_POSES:
            return False
        e1, e0 = st.holdout_errors[self.edge], self.geo.holdout_errors[self.edge]
        alpha_val = self.run.options.levels.validation
        return S.rmse(e1) > S.rmse(e0) and S.paired_test(e1, e0, ordered=self.run.trajectory).p_value < alpha_val

    def edge_rmse(self, st) -> float | None:
        return S.rmse(st.holdout_errors[self.edge]) * 1e3 if bool(self.edge.any()) else None

    def holds(self, st) -> bool:
        """Whether stage ``st`` passes: below the kinematic calibration overall, not worse at the edges."""
        return bool(st.rmse < self.geo.rmse) and not self.edge_worse(st)

    def evidence(self) -> dict:
        """report.json ``holdout_guard``: the rule, every stage's held-out RMSE, whether it was judged and passed."""
        run, geo = self.run, self.geo
        judged = len(run.holdout_idx) >= GUARD_MIN_POSES
        return {
            "rule": "the final model's held-out RMSE must be below the kinematic calibration's, and on the held-out "
            f"poses at the edges of the joint ranges (a joint beyond the {HOLDOUT_EDGE:.1%} / {1 - HOLDOUT_EDGE:.1%} "
            "quantiles of the training poses) not significantly above it; otherwise the run keeps the last stage "
            f"that is, or the kinematic calibration. Judged on {GUARD_MIN_POSES} held-out poses or more",
            "geometric_rmse_mm": geo.rmse * 1e3,
            "n_edge": self.n_edge,
            "stages": [
                {"name": s.name, "rmse_holdout_mm": s.rmse * 1e3, "rmse_edge_mm": self.edge_rmse(s)}
                for s in run.stages[self.i_geo :]
            ],
            "judged": judged,
            "passed": not judged or self.holds(run.stages[-1]),
        }

    def kept_index(self) -> int:
        """The last stage that holds, else the geometric one (the stages are nested: each holds the model as it
        stood)."""
        stages = self.run.stages
        return next(j for j in range(len(stages) - 1, self.i_geo - 1, -1) if j == self.i_geo or self.holds(stages[j]))

    def step_back_reason(self, k: int) -> str:
        """Why the run steps back to stage ``k``, in the words of the report."""
        geo, final, kept = self.geo, self.run.stages[-1], self.run.stages[k]
        lost = (
            f"({geo.rmse * 1e3:.4f} -> {final.rmse * 1e3:.4f} mm)"
            if final.rmse >= geo.rmse
            else f"at the edges of the joint ranges ({self.n_edge} poses: {self.edge_rmse(geo):.4f} -> "
            f"{self.edge_rmse(final):.4f} mm), though better in the middle"
        )
        kept_words = (
            "the kinematic calibration"
            if k == self.i_geo
            else f"the model as it stood after {kept.name} ({kept.rmse * 1e3:.4f} mm)"
        )
        return (
            f"held-out guard: the final model is worse than the kinematic calibration on the held-out poses "
            f"{lost}; the run keeps {kept_words}"
        )


def guard_stages(run: CalibrationRun) -> StageResult:
    """The ``auto`` method never ends worse than the kinematic calibration on the held-out poses.

    The closed loop and the learned stage confirm every effect on validation poses cut from the training poses;
    an effect fitted jointly with the geometry can still win there and extrapolate badly elsewhere: those poses
    test it among the poses it was fitted on, not beyond them, where a trajectory's held-out samples continue the
    path (docs/integrated.md, *The default method on a trajectory*). Where the final model's held-out RMSE is not
    below the geometric stage's, the run steps back to the last stage whose held-out RMSE is (the stages are
    nested: each holds the model as it stood), or to the kinematic calibration when none is; the effects of the
    stages dropped become rejections that say why, with the held-out errors of every stage
    (``run.holdout_guard``, report.json ``holdout_guard``). The held-out RMSE reported is then that of a model the
    held-out poses helped choose; the guard only ever steps back towards the geometry, never adds anything.

    The result's ``holdout_guard`` is the evidence (None where the run has no stage after the geometric one or no
    held-out poses).
    """
    work = StageWork(run, "held-out guard", model=run.model)  # the model is only replaced, never edited
    if run.stages[-1] is run.stage(StageName.GEOMETRIC) or len(run.holdout_idx) == 0:
        return work.result(model_changed=False)
    view = _GuardView.of(run)
    evidence = view.evidence()
    work.holdout_guard = evidence
    if not evidence["judged"]:
        note = (
            f"held-out guard: not judged, {len(run.holdout_idx)} held-out pose(s) (fewer than {GUARD_MIN_POSES}); "
            "the stages stand on their validation poses"
        )
        work.note(note)
        _console.info(note)
        return work.result(model_changed=False)
    if evidence["passed"]:
        return work.result(model_changed=False)
    k = view.kept_index()
    evidence["kept_stage"] = run.stages[k].name
    reason = view.step_back_reason(k)
    _step_back(work, run, k, reason, evidence)
    work.note(reason)
    _console.info(reason)
    return work.result()


def _step_back(work: StageWork, run: CalibrationRun, k: int, reason: str, evidence: dict) -> None:
    """Keep the run's stages up to ``k``: the effects of the later ones become rejections that say why, the model
    is stage ``k``'s, and the fits and what stays unexplained are those of its own fit."""
    kept = run.stages[k]
    kept_names = {s.name for s in run.stages[: k + 1]}
    dropped = [r for r in run.effects if r.label not in kept_names]
    for rec in dropped:
        work.rejections.append(
            Rejection(
                rec.kind,
                rec.joint,
                {"params": rec.params, "admitted_by": rec.evidence, "holdout_guard": evidence},
                name=rec.name or rec.label,
                reason=reason,
                cause=Cause.HOLDOUT_GUARD,
            )
        )
    work.effects[:] = [r for r in run.effects if r.label in kept_names]
    del work.stages[k + 1 :]
    work.model = copy.deepcopy(kept.model)
    # the report's global test, parameters and unexplained structure: those of the kept stage's own fit (the
    # geometric one, or the joint refit that admitted the kept effect), not of a fit the dropped stages added
    n = max((j for j, f in enumerate(run.fits) if f.stage == kept.name), default=None)
    if n is None:
        return
    del work.fits[n + 1 :]
    diag = work.diagnosis
    if diag is not None and not work.fits[-1].global_test.get("passed", True):
        ctx = Context.from_measurements(run.train, trajectory=run.trajectory)
        why = {f"q{r.joint}" if r.joint else "t": reason for r in dropped}
        diag.unexplained = unexplained_entries(
            work.model, ctx, run.train.p, work.fits[-1], run.options.levels.score, why
        )
