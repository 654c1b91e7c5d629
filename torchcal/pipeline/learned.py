"""The learned stage of a work: a residual model where the data demand it, and the correction network.

* ``auto``: :func:`learned_stage`: an additive + ARD Gaussian process (:mod:`torchcal.effects.gp`), a kernel
  regression (:mod:`torchcal.effects.kernel`; only up to :data:`KERNEL_CANDIDATE_MAX` fitting poses) and the
  correction network are fitted on 80 % of the training poses and judged on the other 20 %; the
  best is kept when it lowers the validation RMSE by at least 5 % and a one-sided paired test gives p < 0.01;
  then geometry and learned model are refitted in turn (:func:`refine_learned`), each named effect the learned
  model explains as well is dropped (:func:`prune_named`), and a kept GP is conditioned on all training poses
  (:func:`condition_on_all`).
* ``pcm``, ``kinematic+ann``: :func:`correction_net_stage`: the paper's correction network on what remains,
  early-stopped on a seeded 20 % of the training poses.
"""

from __future__ import annotations

import copy
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import torch

from torchcal import _console
from torchcal import stats as S
from torchcal._threads import torch_threads
from torchcal.data import Measurements
from torchcal.diagnose.tracing import unexplained_after_learned
from torchcal.effects import Context, CorrectionNet, Effect, LearnedEffect, MeasurementModel
from torchcal.effects.gp import GPConditioner, GPCorrection, GPSettings, condition_gp, fit_gp_correction
from torchcal.effects.grouped import GroupedCorrection
from torchcal.effects.kernel import fit_kernel_correction
from torchcal.effects.registry import NAMED_KINDS
from torchcal.errors import EstimationError
from torchcal.estimate.fit import GEOMETRIC_GROUPS, Fit, corrections, solve
from torchcal.estimate.netfit import NetFitResult, fit_net
from torchcal.pipeline.options import Options
from torchcal.pipeline.records import Cause, EffectRecord, Rejection, StageName
from torchcal.pipeline.state import CalibrationRun, StageResult, StageWork

Tensor = torch.Tensor

#: LM iterations of a refit with the learned model in place (:func:`_refit_with_learned`)
REFIT_MAX_ITER = 10
#: the most fitting poses at which the dense kernel regression competes: beyond, its dozen dense solves cost more
#: than the Gaussian process (exact up to 3000 rows, GPSettings.max_exact), which models the same smooth residual
#: fields and uses every pose anyway (docs/methods.md, *The split and the methods*)
KERNEL_CANDIDATE_MAX = 1000
#: the fewest rows of a ``(station, probe)`` group with a learned correction of its own (:func:`_grouped_candidate`)
GROUP_MIN_ROWS = 50


def learned_stage(run: CalibrationRun) -> StageResult:
    """The ``auto`` method's learned stage (module docstring); adds the ``learned`` checkpoint when a model is kept."""
    work = StageWork(run, "learned")
    if not run.options.learned.enabled:
        return work.result(model_changed=False)
    # its fits pin their own threads (the GP's evidence and posterior, the LM refits); the model evaluations between
    # them are small kernels too, so the whole stage runs on one, as the closed loop does
    with torch_threads(1):
        _learned(work, run.train, run.trajectory)
    return work.result()


def _learned(work: StageWork, train: Measurements, trajectory: bool) -> None:
    record = select_learned(work, train, trajectory)
    if record is None:
        return
    gp = None if work.options.learned.hyper else _conditioner(work, train, trajectory)
    e_val = refine_learned(work, record, train, trajectory, gp=gp)
    if any(e.kind in NAMED_KINDS for e in work.model.effects):
        prune_named(work, train, trajectory, e_val, gp=gp)
    condition_on_all(work, train, trajectory)
    before = work.stages[-1]
    after = work.add_stage(StageName.LEARNED)
    record.rmse_before_mm, record.rmse_after_mm = before.rmse * 1e3, after.rmse * 1e3
    diag = work.diagnosis
    if diag is not None and diag.unexplained:
        diag.unexplained = unexplained_after_learned(
            work.model, work.fits[-1], diag.unexplained, train, trajectory, work.options.levels.score
        )


def condition_on_all(work: StageWork, train: Measurements, trajectory: bool) -> None:
    """A kept Gaussian process conditioned on every training pose, its hyperparameters as fitted.

    It was fitted and judged on the learned stage's fitting poses alone; the validation poses, a fifth of the
    training poses, would otherwise never inform the final model (the kernel regression already refits on all).
    """
    model = work.model
    index = len(model.effects) - 1
    eff = model.effects[index]
    if isinstance(eff, GroupedCorrection):
        if not any(isinstance(e, GPCorrection) for e in eff.inner):
            return
        others = MeasurementModel(model.robot, [e for i, e in enumerate(model.effects) if i != index])
        corr = corrections(others, train, trajectory)
        ctx = Context.from_measurements(train, trajectory=trajectory)
        keys, inverse = _groups(train)
        inner = list(eff.inner)
        for k, (key, sub) in enumerate(zip(eff.groups, eff.inner)):
            if isinstance(sub, GPCorrection):
                rows = torch.nonzero(inverse == _group_index(keys, key)).flatten()
                inner[k] = condition_gp(sub, ctx.subset(rows), corr[rows], _gp_settings(work))
        model.effects[index] = GroupedCorrection(eff.groups, inner, eff.regions)
        work.note("learned residual model: each group's Gaussian process conditioned on all its training poses")
        return
    if not isinstance(eff, GPCorrection):
        return
    others = MeasurementModel(model.robot, [e for i, e in enumerate(model.effects) if i != index])
    corr = corrections(others, train, trajectory)
    ctx = Context.from_measurements(train, trajectory=trajectory)
    model.effects[index] = condition_gp(eff, ctx, corr, _gp_settings(work))
    work.note(f"learned residual model: the Gaussian process conditioned on all {train.n} training poses")


def _conditioner(work: StageWork, train: Measurements, trajectory: bool) -> GPConditioner | None:
    """When the kept model is a GP: its posterior's input-only factors on the learned stage's fitting poses, so that
    the alternating refits and the pruning of named effects re-condition it on new corrections with its
    hyperparameters held (:class:`~torchcal.effects.gp.GPConditioner`) instead of refitting them
    (``Options.learned_hyper`` False).

    An evidence fit and an ``O(n m^2)`` posterior per refit cost most of the learned stage's time; held, they cost
    nothing after the first. The hyperparameters then do not follow the residual field a dropped effect leaves,
    so the pruning's paired tests see slightly different validation errors (a borderline decision can change).
    """
    eff = work.model.effects[len(work.model.effects) - 1]
    fi, va = _learned_split(train, work.options.seed, work.options.split.group_tol, trajectory)
    if isinstance(eff, GroupedCorrection):  # one per group's GP, on the group's fitting and validation rows
        keys, inverse = _groups(train)
        out = {}
        for key, sub in zip(eff.groups, eff.inner):
            if isinstance(sub, GPCorrection):
                fg, vg, _ = _group_split(inverse, _group_index(keys, key), fi, va)
                threads = _gp_settings(work).threads
                out[key] = GPConditioner(sub, Context(q=train.q[fg]), Context(q=train.q[vg]), threads=threads)
        return out or None
    if not isinstance(eff, GPCorrection):
        return None
    return GPConditioner(eff, Context(q=train.q[fi]), Context(q=train.q[va]), threads=_gp_settings(work).threads)


def _gp_settings(work: StageWork) -> GPSettings:
    return GPSettings(seed=int(work.options.seed))


def _fit_gp(work: StageWork, train: Measurements, corr: Tensor, fi: Tensor, va: Tensor, warm=None):
    """A GP fitted to the corrections of the fitting poses ``fi`` and judged on the validation poses ``va``
    (:func:`~torchcal.effects.gp.fit_gp_correction`; ``warm``: a previous fit to start from)."""
    return fit_gp_correction(
        Context(q=train.q[fi]),
        corr[fi],
        _gp_settings(work),
        ctx_val=Context(q=train.q[va]),
        y_val=corr[va],
        warm=warm,
        summary=warm is None,  # a refit's variable shares and coverage are never read
    )


def _learned_split(train: Measurements, seed: int, group_tol: float, trajectory: bool = False) -> tuple[Tensor, Tensor]:
    """The fitting and validation poses of the learned stage (in random order, as drawn).

    On a trajectory the validation poses are the last block of the training samples: neighbouring samples
    share their error, and a random share of them lets a learned model be judged on samples it has all but
    seen (it then wins validation and loses on the path's continuation).
    """
    n_val = S.validation_count(train.n)
    if trajectory:
        idx = torch.arange(train.n)
        return idx[: train.n - n_val], idx[train.n - n_val :]
    return tuple(S.split(train.n, n_val, seed=seed + S.Stream.VALIDATION, q=train.q, group_tol=group_tol, sort=False))


def _groups(train: Measurements) -> tuple[Tensor, Tensor] | None:
    """The groups ``(G, 2)`` and each training row's ``(station, probe)`` group index ``(N,)``, or None when the data
    carry one group only. Both on the CPU, as the splits' row indices are: CPU indices index tensors on any device,
    while indices on a GPU cannot index the CPU's."""
    st, pr = getattr(train, "station", None), getattr(train, "probe", None)
    if st is None and pr is None:
        return None
    zero = torch.zeros(train.n, dtype=torch.long, device=train.q.device)
    key = torch.stack([zero if st is None else st.to(torch.long), zero if pr is None else pr.to(torch.long)], 1)
    keys, inverse = torch.unique(key, dim=0, return_inverse=True)
    if len(keys) < 2:
        return None
    return keys.cpu(), inverse.cpu()


def _group_index(keys: Tensor, key: tuple[int, int]) -> int:
    """The index of group ``key`` among ``keys`` (:func:`_groups`)."""
    return next(i for i, k in enumerate(keys.tolist()) if tuple(k) == tuple(key))


def _group_split(inverse: Tensor, g: int, fi: Tensor, va: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Group ``g``'s fitting rows, its validation rows and their positions in ``va``."""
    in_va = inverse[va] == g
    return fi[inverse[fi] == g], va[in_va], torch.nonzero(in_va).flatten()


def _grouped_candidate(work: StageWork, train: Measurements, corr: Tensor, fi: Tensor, va: Tensor) -> tuple | None:
    """Where the data carry several ``(station, probe)`` groups: one learned correction per group of at least
    :data:`GROUP_MIN_ROWS` rows (the best of a GP, a kernel regression and a network on the group's fitting rows,
    judged on its validation rows; none where no candidate lowers its validation RMSE), as one
    :class:`~torchcal.effects.grouped.GroupedCorrection`; its validation errors on all of ``va``. None on one group."""
    found = _groups(train)
    if found is None:
        return None
    keys, inverse = found
    e_val = corr[va].norm(dim=-1).clone()
    effs, groups, regions, described = [], [], [], []
    for g, key in enumerate(keys.tolist()):
        fg, vg, pos = _group_split(inverse, g, fi, va)
        chosen = None
        if len(fg) + len(vg) >= GROUP_MIN_ROWS and len(vg) >= 3:
            cands = _fit_candidates(work, train, corr, fg, vg, who=f"group {tuple(key)}: ")
            best = min(cands, key=lambda k: S.rmse(cands[k][1]))
            eff, e_g, _ = cands[best]
            if S.rmse(e_g) < S.rmse(corr[vg].norm(dim=-1)):  # a group no candidate helps keeps no correction
                chosen = best
                effs.append(eff)
                groups.append(key)
                q_g = train.q[inverse == g]  # the joints this group was measured over: its correction fades beyond
                regions.append(torch.stack([q_g.min(0).values, q_g.max(0).values]))
                e_val[pos] = e_g
        described.append({"station": key[0], "probe": key[1], "rows": len(fg) + len(vg), "model": chosen})
    if not effs:
        return None
    eff = GroupedCorrection(groups, effs, regions)
    return eff, e_val, {"model": "one learned correction per station and probe", "groups": described}


def _fit_candidates(
    work: StageWork, train: Measurements, corr: Tensor, fi: Tensor, va: Tensor, who: str = ""
) -> dict[str, tuple[Effect, Tensor, dict]]:
    """The learned candidates fitted to the corrections ``corr`` at the fitting rows ``fi``: name -> (effect, its
    validation errors at ``va``, its description), in the order GP, kernel regression, network (a GP whose evidence
    fit diverged and a kernel regression over :data:`KERNEL_CANDIDATE_MAX` fitting rows are left out, with a note;
    ``who`` prefixes the notes)."""
    model, opts = work.model, work.options
    # the three candidates are independent: the GP's evidence fit (large kernels, which release the GIL) runs in a
    # second thread beside the network's and the kernel regression's, so that a second core takes half of this
    # step's time; every fit on one torch thread (the GP's own fits pin one), so that the results do not depend on
    # the interleaving
    with torch_threads(1), ThreadPoolExecutor(max_workers=1, initializer=torch.set_num_threads, initargs=(1,)) as pool:
        gp_job = pool.submit(_fit_gp, work, train, corr, fi, va)
        init = torch.Generator().manual_seed(int(opts.seed) + S.Stream.NETWORK_INIT)
        net, res = _fitted_network(model, opts, init=init, q=train.q, corr=corr, fit_i=fi, val_i=va)
        with torch.no_grad():
            e_net = (corr[va] - net(train.q[va])).norm(dim=-1)
        kernel = None
        if len(fi) <= KERNEL_CANDIDATE_MAX:
            kernel = fit_kernel_correction(
                model.robot, train.q[fi], corr[fi], q_val=train.q[va], y_val=corr[va], seed=opts.seed
            )
        candidates = {}
        try:
            gp, gp_info = gp_job.result()
            candidates["gp"] = (
                gp,
                gp_info["val_errors"],
                {
                    **gp.describe(),
                    "model": f"{'exact' if gp.exact else 'sparse'} additive + ARD Gaussian process",
                    "variable_share": gp_info.get("variable_share"),
                    "validation_coverage_2sigma": gp_info.get("val_coverage_2sigma"),
                },
            )
        except EstimationError as err:  # its evidence fit diverged: the other candidates compete without it
            work.note(f"learned residual model: {who}the Gaussian process was left out ({err})")
    if kernel is not None:
        kern, info = kernel
        candidates["kernel"] = (kern, info["val_errors"], kern.describe())
    else:  # a dozen dense solves of that size, for a candidate the GP covers (KERNEL_CANDIDATE_MAX)
        work.note(
            f"learned residual model: {who}the dense kernel regression is left out ({len(fi)} fitting poses, "
            f"more than the {KERNEL_CANDIDATE_MAX} at which it competes)"
        )
    candidates["network"] = (
        LearnedEffect(net),
        e_net,
        {
            "model": "network",
            "hidden": opts.network.hidden,
            "n_weights": net.n_weights,
            "fit": res.method,
            "best_iteration": res.best_iteration,
        },
    )
    return candidates


def select_learned(
    work: StageWork, train: Measurements, trajectory: bool, min_gain: float = 0.05, alpha: float = 0.01
) -> EffectRecord | None:
    """Add the better of a kernel correction and a correction network if it earns its place (module docstring).

    Returns the record of the kept model (appended to the work), or None when neither earned its place.
    """
    model, opts = work.model, work.options
    corr = corrections(model, train, trajectory)
    fi, va = _learned_split(train, opts.seed, opts.split.group_tol, trajectory)
    e0 = corr[va].norm(dim=-1)
    candidates = _fit_candidates(work, train, corr, fi, va)
    grouped = _grouped_candidate(work, train, corr, fi, va)
    if grouped is not None:
        candidates["grouped"] = grouped
    name = min(candidates, key=lambda k: S.rmse(candidates[k][1]))
    effect, e1, params = candidates[name]
    rmse0, rmse1 = S.rmse(e0), S.rmse(e1)
    test = S.paired_improvement(e0, e1)
    evidence = {
        "candidates_validation_rmse_mm": {k: S.rmse(v[1]) * 1e3 for k, v in candidates.items()},
        "chosen": name,
        "validation_rmse_before_mm": rmse0 * 1e3,
        "validation_rmse_after_mm": rmse1 * 1e3,
        "relative_gain": 1.0 - rmse1 / rmse0 if rmse0 > 0 else 0.0,
        **test.to_dict(),
        "rule": f"relative gain >= {min_gain:.0%} and p < {alpha}",
        "n_validation": len(va),
    }
    accepted = evidence["relative_gain"] >= min_gain and test.p_value < alpha
    work.note(
        f"learned residual model: {name} {'accepted' if accepted else 'rejected'} "
        f"(validation {rmse0 * 1e3:.4f} -> {rmse1 * 1e3:.4f} mm, p = {test.p_value:.2g})"
    )
    if not accepted:
        work.rejections.append(Rejection("learned", None, evidence, cause=Cause.SELECTION))
        return None
    model.add(effect)
    work.learned_validation_errors = e1
    record = EffectRecord("learned", None, params, evidence, name="learned", label="learned")
    work.effects.append(record)
    return record


def _refit_with_learned(
    work: StageWork, model: MeasurementModel, train: Measurements, trajectory: bool, gp: GPConditioner | None = None
) -> tuple[Fit, Tensor]:
    """One alternating round on ``model`` (its last effect is the learned one): the geometry and the named
    effects with the learned correction in place, then the learned model on the new corrections.

    Returns the least-squares fit and the learned model's validation errors per pose ``(n_val,)`` [m];
    a refitted kernel or GP replaces the old one in ``model``. ``gp``: a GP is re-conditioned through it, its
    hyperparameters held (:func:`_conditioner`), instead of refitted.
    """
    fit, corr = _refit_geometry(work, model, train, trajectory)
    return fit, _refit_learned_model(work, model, train, trajectory, corr, gp)


def _refit_geometry(
    work: StageWork, model: MeasurementModel, train: Measurements, trajectory: bool
) -> tuple[Fit, Tensor]:
    """The first half of :func:`_refit_with_learned`: the least-squares refit with the learned correction in place;
    returns it and the corrections ``(N, 3)`` [m] that the learned model is then refitted to."""
    opts = work.options
    index = len(model.effects) - 1
    ida = work.identifiability
    groups = GEOMETRIC_GROUPS if ida is not None else ("instrument", "tool")
    # warm-started from the current fit and used to compare models, the refit needs few iterations; where the
    # valley is flat (real data) an uncapped LM crawls on without changing the comparison
    fit = solve(
        model,
        train,
        groups,
        replace(opts.fit, max_iter=min(opts.fit.max_iter, REFIT_MAX_ITER)),
        "learned (alternating refit)",
        trajectory=trajectory,
        effects=True,
        identifiability=ida,
    )
    others = MeasurementModel(model.robot, [e for i, e in enumerate(model.effects) if i != index])
    return fit, corrections(others, train, trajectory)


def _refit_learned_model(
    work: StageWork,
    model: MeasurementModel,
    train: Measurements,
    trajectory: bool,
    corr: Tensor,
    gp: GPConditioner | None = None,
) -> Tensor:
    """The second half of :func:`_refit_with_learned`: the learned model (``model``'s last effect) refitted to the
    corrections ``corr``; returns its validation errors ``(n_val,)`` [m]."""
    opts = work.options
    index = len(model.effects) - 1
    fi, va = _learned_split(train, opts.seed, opts.split.group_tol, trajectory)
    model.effects[index], e_val = _refit_one(work, model.effects[index], train, corr, fi, va, gp=gp)
    return e_val


def _refit_one(
    work: StageWork,
    eff: Effect,
    train: Measurements,
    corr: Tensor,
    fi: Tensor,
    va: Tensor,
    *,
    gp: GPConditioner | dict | None = None,
) -> tuple[Effect, Tensor]:
    """A learned correction ``eff`` refitted to the corrections ``corr`` at the fitting rows ``fi``; the refitted
    correction and its validation errors at ``va``. A grouped correction refits each group's on its own rows."""
    opts = work.options
    if isinstance(eff, GroupedCorrection):
        keys, inverse = _groups(train)
        e_val = corr[va].norm(dim=-1).clone()
        inner = []
        for key, sub in zip(eff.groups, eff.inner):
            fg, vg, pos = _group_split(inverse, _group_index(keys, key), fi, va)
            new, e_val[pos] = _refit_one(
                work, sub, train, corr, fg, vg, gp=gp.get(key) if isinstance(gp, dict) else None
            )
            inner.append(new)
        return GroupedCorrection(eff.groups, inner, eff.regions), e_val
    if isinstance(eff, LearnedEffect):
        fit_net(
            eff.net,
            train.q[fi],
            corr[fi],
            val=(train.q[va], corr[va]),
            method=opts.network.method,
            iterations=opts.network.iterations,
            ftol=1e-6,
        )
        with torch.no_grad():
            e_val = (corr[va] - eff.net(train.q[va])).norm(dim=-1)
        return eff, e_val
    if isinstance(eff, GPCorrection) and gp is not None:
        new, info = gp.condition(corr[fi], corr[va])
        return new, info["val_errors"]
    if isinstance(eff, GPCorrection):
        new, info = _fit_gp(work, train, corr, fi, va, warm=eff)
        return new, info["val_errors"]
    new, info = fit_kernel_correction(
        work.model.robot,
        train.q[fi],
        corr[fi],
        q_val=train.q[va],
        y_val=corr[va],
        seed=opts.seed,
        start=(float(eff.length_scale), float(eff.noise_ratio)),  # new corrections, near the old: search locally
    )
    return new, info["val_errors"]


def refine_learned(
    work: StageWork,
    record: EffectRecord,
    train: Measurements,
    trajectory: bool,
    rounds: int = 3,
    gp: GPConditioner | None = None,
) -> Tensor:
    """Refit the geometry (and the named effects) and the learned model in turn, while validation improves.

    The geometric fit has already bent the geometry towards the part of the non-geometric field
    that looks geometric, and the learned model was fitted to what was left. Alternating the two
    fits (geometry with the learned correction in place, then the learned model on the new
    corrections, on the same fitting and validation poses as :func:`select_learned`) moves the
    pair towards their joint least-squares solution; a round is kept only when the validation
    RMSE of the learned model falls. Returns the learned model's validation errors per pose.
    ``gp``: re-conditions a GP with its hyperparameters held (:func:`_conditioner`).
    """
    model = work.model
    best = record.evidence["validation_rmse_after_mm"] * 1e-3
    best_e = None
    history = [best * 1e3]
    for _ in _console.progress(range(rounds), desc="learned: alternating refits"):
        trial = _trial(model)
        try:
            fit, e_val = _refit_with_learned(work, trial, train, trajectory, gp)
        except EstimationError as err:  # a rank-deficient refit: the model stays as it is, and the work says so
            work.note(f"learned residual model: an alternating refit failed and was not kept ({err})")
            break
        v = S.rmse(e_val)
        if not v < best * (1.0 - 1e-3):
            break
        _adopt(model, trial)
        best, best_e = v, e_val
        history.append(v * 1e3)
        work.fits.append(fit)
    if best_e is None:  # no round helped: the errors of the model as it stands
        best_e = work.learned_validation_errors
    record.evidence["alternating_refit_validation_rmse_mm"] = history
    work.note(
        f"learned residual model: {len(history) - 1} alternating refits of geometry and learned model, "
        f"validation {history[0]:.4f} -> {history[-1]:.4f} mm"
    )
    return best_e


def _trial(model: MeasurementModel) -> MeasurementModel:
    """A copy of ``model`` to refit, sharing its GP (the learned model, when a GP): a refit leaves a GP as it is (its
    buffers are no parameters) and replaces it by a new one, so that a copy would only lose the posterior mean at
    the training poses that the GP keeps (:meth:`GPCorrection.forward`: the same tensor objects), and every refit's
    geometric fit would compute it anew (2218 x 1774 kernel entries on Series C)."""
    learned = model.effects[len(model.effects) - 1] if len(model.effects) else None
    memo = {id(learned): learned} if isinstance(learned, GPCorrection) else {}
    return copy.deepcopy(model, memo)


def _adopt(model: MeasurementModel, other: MeasurementModel) -> None:
    """Make ``model`` hold ``other``'s effects and parameter values (the robot stays the same object)."""
    model.robot.load_state_dict(other.robot.state_dict())
    model.effects = torch.nn.ModuleList(list(other.effects))
    for e in model.effects:
        e.train(False)


def prune_named(
    work: StageWork, train: Measurements, trajectory: bool, e_val: Tensor, gp: GPConditioner | None = None
) -> None:
    """With a learned model in place, drop each named effect the learned model explains as well.

    A smooth field that no named effect describes still projects onto some of their regressors,
    and the loop may accept one for that share. For each named effect in turn, the model without
    it (geometry and learned model refitted as in :func:`refine_learned`) is compared with the
    model with it on the learned stage's validation poses: the effect stays only when the model
    with it is better by a one-sided paired test at ``alpha_validation``.

    A refitted GP's evidence fit (large kernels, which release the GIL) runs in a second thread while the main
    thread refits the geometry without the next effect, on the model as it stands (:class:`_Without`); when the
    effect before is dropped, that refit is discarded and done again on the new model, so the decisions and
    numbers are those of one effect after the other. Every fit on one torch thread, as in :func:`select_learned`.
    """
    model = work.model
    labels = [e.label() for e in model.effects if e.kind in NAMED_KINDS]
    # the learned model is the last effect; only a GP refitted by its evidence runs beside the next geometry refit
    ahead_of_time = isinstance(model.effects[len(model.effects) - 1], GPCorrection) and gp is None
    with torch_threads(1), ThreadPoolExecutor(max_workers=1, initializer=torch.set_num_threads, initargs=(1,)) as pool:
        ahead: _Without | None = None
        for pos, label in enumerate(labels):
            k = next(i for i, e in enumerate(model.effects) if e.label() == label)
            eff = model.effects[k]
            job = ahead if ahead is not None else _Without(work, model, label, train, trajectory)
            job.start(gp, pool)
            ahead = None
            if ahead_of_time and pos + 1 < len(labels):  # the next one's geometry refit while this one's GP refits
                ahead = _Without(work, model, labels[pos + 1], train, trajectory)
            try:
                trial, fit, e_without = job.result()
            except EstimationError as err:  # cannot judge it without the effect: the effect stays
                work.note(f"diagnosis: {eff.label()} kept: the refit without it failed ({err})")
                continue
            if _prune_one(work, model, eff, trial=trial, fit=fit, e_without=e_without, e_val=e_val):
                e_val = e_without
                ahead = None  # refitted on the model with this effect: again on the model without it


class _Without:
    """The model without one named effect, refitted for :func:`prune_named` as :func:`_refit_with_learned` does:
    the geometry when made (in this thread: forward-mode derivatives are not thread-safe), the learned model from
    :meth:`start` (a GP refitted by its evidence in ``pool``, any other at once). :meth:`result` gives
    ``(trial, fit, validation errors)`` or raises the refit's EstimationError."""

    def __init__(self, work: StageWork, model: MeasurementModel, label: str, train: Measurements, trajectory: bool):
        self.work, self.train, self.trajectory = work, train, trajectory
        self.trial = _trial(model)
        del self.trial.effects[next(i for i, e in enumerate(model.effects) if e.label() == label)]
        self.error, self.job, self.e_val = None, None, None
        try:
            self.fit, self.corr = _refit_geometry(work, self.trial, train, trajectory)
        except EstimationError as err:
            self.error = err

    def start(self, gp: GPConditioner | None, pool: ThreadPoolExecutor) -> None:
        if self.error is not None:
            return
        args = (self.work, self.trial, self.train, self.trajectory, self.corr)
        if isinstance(self.trial.effects[len(self.trial.effects) - 1], GPCorrection) and gp is None:
            self.job = pool.submit(_refit_learned_model, *args)
            return
        try:
            self.e_val = _refit_learned_model(*args, gp)
        except EstimationError as err:
            self.error = err

    def result(self) -> tuple[MeasurementModel, Fit, Tensor]:
        if self.error is not None:
            raise self.error
        e_val = self.job.result() if self.job is not None else self.e_val
        return self.trial, self.fit, e_val


def _prune_one(
    work: StageWork,
    model: MeasurementModel,
    eff: Effect,
    *,
    trial: MeasurementModel,
    fit: Fit,
    e_without: Tensor,
    e_val: Tensor,
) -> bool:
    """:func:`prune_named`'s decision on ``eff`` from the refit without it; drops it (``model`` takes ``trial``'s
    effects and values, the work's records say why) and returns True, or records why it stays and returns False."""
    opts = work.options
    test = S.paired_improvement(e_without, e_val)
    evidence = {
        "validation_rmse_with_mm": S.rmse(e_val) * 1e3,
        "validation_rmse_without_mm": S.rmse(e_without) * 1e3,
        **test.to_dict(),
        "rule": f"kept when the model with it is better, one-sided paired p < {opts.levels.validation}",
    }
    entry = next((r for r in work.effects if r.label == eff.label()), None)
    if entry is not None:
        entry = work.amend(entry, with_learned_model=evidence)
    if test.p_value < opts.levels.validation:
        return False
    _adopt(model, trial)
    work.fits.append(fit)
    reason = (
        f"the learned model explains it as well (validation {evidence['validation_rmse_with_mm']:.4f} mm "
        f"with it, {evidence['validation_rmse_without_mm']:.4f} mm without, p = {test.p_value:.2g})"
    )
    work.note(f"diagnosis: {eff.label()} dropped: {reason}")
    if entry is not None:
        work.effects[:] = [r for r in work.effects if r is not entry]
        work.rejections.append(
            Rejection(
                entry.kind,
                entry.joint,
                entry.evidence,
                name=entry.name,
                reason=f"accepted in round {entry.evidence.get('round')}, then dropped: {reason}",
                cause=Cause.EXPLAINED,
            )
        )
    work.stages[:] = [st for st in work.stages if st.name != eff.label()]
    if work.diagnosis is not None:
        work.diagnosis.drop(eff.label(), f"dropped after the learned stage: {reason}")
    return True


def correction_net_stage(run: CalibrationRun) -> StageResult:
    """The ``pcm`` / ``kinematic+ann`` step: a correction network on what remains (paper Eq. 22: corrections in the
    base frame), as the ``learned`` checkpoint."""
    work = StageWork(run, "correction network")
    model, opts = work.model, work.options
    _console.info(f"correction network {model.robot.dof}-{opts.network.hidden}-3 on the remaining position corrections")
    fit_correction_net(work, run.train, run.trajectory)
    before = work.stages[-1]
    after = work.add_stage(StageName.LEARNED)
    work.effects.append(
        EffectRecord(
            "learned",
            None,
            {"hidden": opts.network.hidden, "n_weights": model.effects[-1].net.n_weights, "fit": opts.network.method},
            {"validation": "early stopping on a seeded 20 % of the training poses"},
            rmse_before_mm=before.rmse * 1e3,
            rmse_after_mm=after.rmse * 1e3,
        )
    )
    return work.result()


def fit_correction_net(work: StageWork, train: Measurements, trajectory: bool) -> None:
    """Add a :class:`LearnedEffect` fitted to the training corrections, early-stopped on a validation share."""
    model, opts = work.model, work.options
    corr = corrections(model, train, trajectory)  # R^T (y - f): the correction in the base frame
    g = torch.Generator().manual_seed(int(opts.seed) + S.Stream.CORRECTION_NET)
    # the generator goes on to the network's initial weights and to the fit
    fit_i, val_i = S.split(
        train.n,
        S.validation_count(train.n),
        generator=g,
        q=train.q,
        group_tol=opts.split.group_tol,
        sort=False,
    )
    net, res = _fitted_network(model, opts, init=g, q=train.q, corr=corr, fit_i=fit_i, val_i=val_i, fit_generator=g)
    work.note(
        f"correction network: {res.method} {res.status} after {res.iterations} iterations, "
        f"best validation at {res.best_iteration}"
    )
    model.add(LearnedEffect(net))


def _fitted_network(
    model: MeasurementModel,
    opts: Options,
    *,
    init: torch.Generator,
    q: Tensor,
    corr: Tensor,
    fit_i: Tensor,
    val_i: Tensor,
    fit_generator: torch.Generator | None = None,
) -> tuple[CorrectionNet, NetFitResult]:
    """A :class:`CorrectionNet` of ``opts.network.hidden`` units, initialised from ``init`` and fitted to the
    corrections ``corr`` at the poses ``fit_i`` with early stopping on ``val_i``; the network and the fit's result."""
    net = CorrectionNet(model.robot.dof, opts.network.hidden, device=model.robot.device)
    net.reset_parameters(init, gain=0.5)
    res = fit_net(
        net,
        q[fit_i],
        corr[fit_i],
        val=(q[val_i], corr[val_i]),
        method=opts.network.method,
        iterations=opts.network.iterations,
        generator=fit_generator,
    )
    return net, res
