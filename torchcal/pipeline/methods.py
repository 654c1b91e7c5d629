"""The calibration methods as declared sequences of stages, and the stages every method shares.

A stage reads the run and returns a :class:`~torchcal.pipeline.state.StageResult`; a method is the list of its
stages (:data:`METHOD_TABLE`); :func:`torchcal.pipeline.run.calibrate` applies each result in turn.

* ``kinematic``: kinematic calibration (Horvath & Neuner 2024, Eq. 11): the identifiable DH / joint-origin errors,
  the instrument pose and the lever arm, by weighted LM (then, with ``Options.refit``, fitted again on all samples).
* ``pcm``: the paper's position correction model (Eq. 10 + Sec. 2.2): instrument pose and lever arm with the nominal
  geometry, then a correction network on the position corrections.
* ``kinematic+ann``: the literature's sequential "kinCalib+": ``kinematic``, then the network on what remains.
* ``auto`` (default): ``kinematic``, then the closed loop (:mod:`torchcal.pipeline.loop`): the named effects the
  residuals demand, each chosen by a score test, refitted jointly with the geometry and confirmed on validation
  poses; then a learned residual model only where the data demand it (:mod:`torchcal.pipeline.learned`); then the
  held-out guard (:mod:`torchcal.pipeline.holdout`): never worse than the kinematic calibration.
* ``integrated``: ``kinematic`` (the reference stage), then the integrated ANN-EKF on a continuous trajectory
  (:mod:`torchcal.pipeline.integrated`) with the engine ``Options.engine`` names.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import torch

from torchcal import _console
from torchcal._method import Method
from torchcal._threads import torch_threads
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.estimate.fit import (
    GEOMETRIC_GROUPS,
    fit_covariance,
    place_instrument_and_tool,
    place_tool_rotation,
    prior_scales,
    solve,
)
from torchcal.estimate.identifiability import Detectability, detectability
from torchcal.pipeline.checks import check_corrections
from torchcal.pipeline.holdout import guard_stages, refit_kinematic
from torchcal.pipeline.integrated import integrated_stage
from torchcal.pipeline.learned import correction_net_stage, learned_stage
from torchcal.pipeline.loop import close_loop
from torchcal.pipeline.prior import MAX_RELEASED, MOVED_SIGMAS, moved_words, prior_update, release
from torchcal.pipeline.priorheld import held_alike, held_untold
from torchcal.pipeline.records import Note, StageName
from torchcal.pipeline.state import CalibrationRun, StageFn, StageResult, StageWork


def nominal(run: CalibrationRun) -> StageResult:
    """The baseline: the nominal geometry with the instrument pose and lever arm fitted (closed form, then LM); with a
    6-D probe's orientations also the probe frame's rotation in the flange, and every later fit weighs them too."""
    work = StageWork(run, StageName.NOMINAL)
    train, opts = run.train, run.options
    _console.info(
        f"{work.robot.name}: {train.n} training and {run.hold.n} held-out poses; fitting tracker pose and lever arm"
    )
    noise = float(train.sigma.median()) if train.sigma is not None else opts.fit.sigma_tracker
    place_instrument_and_tool(
        work.robot,
        train.q,
        train.p,
        lever_prior=opts.fit.lever_prior(noise, opts.device),
        station=train.station,
        probe=train.probe,
    )
    if train.r is not None and len(rows := train.orientation_rows):  # a 6-D probe: its frame's rotation in the
        place_tool_rotation(work.robot, train.q[rows], train.r[rows])  # flange, from the orientations (closed form)
    work.fits.append(
        solve(
            work.model,
            train,
            ("instrument", "tool"),
            opts.fit,
            StageName.NOMINAL,
            trajectory=run.trajectory,
            identify=False,
        )
    )
    work.add_stage(StageName.NOMINAL)
    return work.result()


def geometric(run: CalibrationRun) -> StageResult:
    """The kinematic calibration: identifiability analysis and weighted LM over geometry, instrument and lever arm;
    stopped where the corrections are many times their priors (:func:`~torchcal.pipeline.checks.check_corrections`)."""
    work = StageWork(run, StageName.GEOMETRIC)
    _console.info("kinematic calibration: identifiability analysis and weighted LM")
    fit = solve(
        work.model,
        run.train,
        GEOMETRIC_GROUPS,
        run.options.fit.geometric(),
        StageName.GEOMETRIC,
        trajectory=run.trajectory,
    )
    check_corrections(fit, work.model, run.options, run.data)
    work.fits.append(fit)
    work.add_stage(StageName.GEOMETRIC)
    return work.result()


def nominal_geometry(run: CalibrationRun) -> StageResult:
    """The ``geometric`` checkpoint of a method that keeps the nominal geometry (the paper's position correction
    model): the story's reference is the baseline itself."""
    work = StageWork(run, StageName.GEOMETRIC, model=run.model)
    work.add_stage(StageName.GEOMETRIC)
    return work.result(model_changed=False)


def closed_loop(run: CalibrationRun) -> StageResult:
    """The closed loop (:func:`~torchcal.pipeline.loop.close_loop`), where ``Options.diagnose`` asks for it."""
    if not run.options.loop.enabled:
        return StageResult("closed loop")
    _console.info("diagnosis: score tests of the candidate effects, joint refits, validation")
    # small kernels throughout (u x u solves, one pass over the poses, score tests, smooths): one thread, so that
    # another process on the machine does not multiply the time (torch's threads spin while one waits for a core)
    with torch_threads(1):
        return close_loop(run)


def learned(run: CalibrationRun) -> StageResult:
    """The learned residual model (:func:`~torchcal.pipeline.learned.learned_stage`)."""
    if run.options.learned.enabled:
        _console.info("residual model: kernel regression and correction network judged on validation poses")
    return learned_stage(run)


def guard(run: CalibrationRun) -> StageResult:
    """Never worse than the kinematic calibration on the held-out poses (:func:`~torchcal.pipeline.holdout.
    guard_stages`)."""
    with torch_threads(1):
        return guard_stages(run)


def prior_start(run: CalibrationRun) -> StageResult:
    """The baseline of a calibration from a prior run (:mod:`torchcal.pipeline.prior`): the prior run's model as it
    stands, on the new poses (no fit: its instrument pose and lever arm are the prior's too)."""
    work = StageWork(run, StageName.NOMINAL)
    _console.info(
        f"{work.robot.name}: {run.train.n} training and {run.hold.n} held-out poses; starting from {run.prior.source}"
    )
    work.note(
        f"prior: started from {run.prior.source}; {len(run.prior.sigma)} parameters may change (MAP about its "
        f"values), its {len(run.model.effects)} effect(s) held; the 'nominal' stage is the prior run's model"
    )
    work.add_stage(StageName.NOMINAL)
    return work.result(model_changed=False)


def _fit_about_prior(run: CalibrationRun, rows, stage: str):
    """The MAP fit of the geometry, instrument pose and lever arm about the prior on ``rows``, from the prior's
    values, with the priors that fail their test released one at a time (:func:`prior_geometric`). No
    identifiability analysis: every element has its prior, so the normal matrix is regular, and an element held
    where the rows add little to its prior could not show that it changed. Returns the model and the fit."""
    released: list[str] = []
    tool = [i.name for i in run.prior.model.robot.parameter_info() if i.group == "tool" and i.name in run.prior.sigma]

    def fitted(names: list[str]):
        model = copy.deepcopy(run.model)
        model.robot.prior_sigma = release(run.prior, names, run.options.fit)
        fit = solve(model, rows, GEOMETRIC_GROUPS, run.options.fit, stage, trajectory=run.trajectory, identify=False)
        return model, fit

    model, fit = fitted(released)
    while True:
        worst = prior_update(run.prior, model).worst
        if worst is None or len(released) >= MAX_RELEASED:
            return model, fit, released
        # a changed tool is one vector: released one component at a time, a few poses put the rest of a 20 mm tool
        # change into the wrist's elements (a5 57 mm, theta5 17 deg on a UR10: refused as implausible). Its lever arm
        # is released whole where one of its components fails its test, or where that fits the rows better than
        # releasing the worst element
        rest = [n for n in tool if n not in released]
        options = [released + rest] if worst in tool else [released + [worst]]
        if worst not in tool and rest:
            options.append(released + rest)
        tried = [(names, *fitted(names)) for names in options]
        released, model, fit = min(tried, key=lambda t: t[2].result.cost_history[-1])


def prior_geometric(run: CalibrationRun) -> StageResult:
    """The kinematic calibration from a prior run: MAP about its values; a prior that fails its test (a change
    beyond :data:`~torchcal.pipeline.prior.MOVED_SIGMAS` of its sigma) is released, largest first, one at a time, and
    the fit repeated (:func:`~torchcal.pipeline.prior.release`): a Gaussian prior pulls a real change back by the
    square of its size and spreads it over its correlated neighbours, where a released one lets the poses fit it."""
    work = StageWork(run, StageName.GEOMETRIC)
    _console.info("kinematic calibration about the prior run: MAP, the changed parameters released")
    model, fit, released = _fit_about_prior(run, run.train, StageName.GEOMETRIC)
    check_corrections(fit, model, run.options, run.data)
    if released:
        work.note(f"prior: released (changed beyond {MOVED_SIGMAS:g} prior sigma): {', '.join(released)}")
    work.model = model
    work.fits.append(fit)
    work.add_stage(StageName.GEOMETRIC)
    return work.result()


def prior_refit(run: CalibrationRun) -> StageResult:
    """With ``Options.refit``, the fit about the prior again on all rows, training and held-out (the held-out errors
    reported stay the training fit's)."""
    work = StageWork(run, "refit")
    if not run.options.refits:
        return work.result(model_changed=False)
    both = run.fitted_and_held_out
    _console.info(f"geometry fitted again about the prior on all {both.n} samples")
    work.model, fit, _ = _fit_about_prior(run, both, "refit: geometry on all samples")
    work.fits.append(fit)
    work.note(f"refit: the model written was fitted again about the prior on all {both.n} samples")
    return work.result()


def prior_moved(run: CalibrationRun) -> StageResult:
    """What the new poses changed of the prior run: each parameter's change in its prior sigmas, and the moved ones
    (:func:`~torchcal.pipeline.prior.prior_update`)."""
    update = prior_update(run.prior, run.model)
    alike = held_alike(run, list(run.fits[-1].free.names)) if update.moved else {}
    alike = tuple((n, tuple(alike[n])) for n in update.moved if alike.get(n))
    update = dataclasses.replace(update, detect=_detectability(run, update), alike=alike)
    told = moved_words(update.moved, dict(alike)) or "none"
    notes = [f"prior: moved beyond {update.threshold:g} prior sigma: {told}"]
    if update.detect is not None and update.detect.untold:
        notes[0] += " of what these rows can tell"
        notes += untold_messages(update.detect)
    for n in notes:
        _console.info(n)
    return StageResult("prior", notes=tuple(Note("prior", n) for n in notes), prior_update=update)


def _detectability(run: CalibrationRun, update) -> Detectability | None:
    """Whether the last fit about the prior could have told a move of each prior parameter
    (:func:`~torchcal.estimate.identifiability.detectability`), or None where its normal matrix is singular."""
    fit = run.fits[-1]
    if fit.result.normal is None:
        return None
    scales = prior_scales(run.model, run.options.fit)
    inf = float("inf")
    N = fit.result.normal
    fit_sigma = torch.tensor([scales.get(n, inf) for n in fit.free.names], dtype=N.dtype, device=N.device)
    test_sigma = torch.tensor([run.prior.sigma.get(n, inf) for n in fit.free.names], dtype=N.dtype, device=N.device)
    try:
        rows = len(fit.whitening) if fit.whitening is not None else 0
        d = detectability(fit.free.names, N, fit_sigma, test_sigma, rows)
    except torch.linalg.LinAlgError:
        return None
    # the untold that already changed most first: a move the rows saw in part (theta2 at 2.9 of its 10 sigma) and
    # spread over its neighbours is the one a user must hear of
    ratio = {r["name"]: r["ratio"] for r in update.rows}
    untold = [{**u, "change_sigma": ratio.get(u["name"])} for u in d.untold]
    untold = sorted(untold, key=lambda u: -(u["change_sigma"] or 0.0))
    # what the prior run held the update holds: no poses let it name their move, which goes to the free ones
    held = held_untold(run, list(fit.free.names), d.k)
    return dataclasses.replace(d, untold=(*untold, *held))


def untold_messages(d: Detectability) -> list[str]:
    """The notes and stderr lines of the parameters a calibration from a prior could not have seen move: those its
    rows cannot tell, then those the prior run held (:func:`~torchcal.pipeline.priorheld.held_untold`)."""
    free = [u for u in d.untold if not u.get("held")]
    held = [u for u in d.untold if u.get("held")]
    parts = [_free_message(d, free)] if free else []
    if held:
        names = ", ".join(u["name"] for u in held[:8]) + (f" and {len(held) - 8} more" if len(held) > 8 else "")
        goes = [n for u in held for n in u["absorbed_by"]]
        goes = list(dict.fromkeys(goes))
        parts.append(
            f"prior: the prior run could not determine {names}, and this update holds them at its values: a move of "
            f"theirs cannot be named by any poses"
            + (f" (it would go to {', '.join(goes[:6])})" if goes else "")
            + "; to tell them, calibrate from scratch on poses torchcal plan --run THIS_RUN chooses"
        )
    return parts


def _free_message(d: Detectability, untold: list[dict]) -> str:
    """:func:`untold_message`'s part of the fitted parameters the rows cannot tell."""
    names = ", ".join(u["name"] for u in untold[:8]) + (f" and {len(untold) - 8} more" if len(untold) > 8 else "")
    told = {u["name"] for u in untold}
    spread = [n for u in untold for n in u["absorbed_by"] if n not in told]
    spread = list(dict.fromkeys(spread))
    first, every = untold[0], d.to_dict()["poses_to_add"]
    more = None if first["rows_needed"] is None else max(first["rows_needed"] - d.rows, 1)
    how = (
        f"add about {more} poses like these to tell {first['name']} ({every if every is not None else 'more'} "
        f"for all; torchcal plan --run THIS_RUN --n {more} chooses better ones) and update again"
        if more
        else f"poses like these never tell {first['name']}: torchcal plan --run THIS_RUN chooses ones that do"
    )
    return (
        f"prior: these rows cannot tell a move of {d.k:g} prior sigma of {names}"
        + (f" (it would go to {', '.join(spread[:6])})" if spread else "")
        + f": they may have moved unseen; {how}"
    )


def finish(run: CalibrationRun) -> StageResult:
    """The model written: its calibrated region (the training rows, or all rows where the run refitted on them;
    from a prior run, together with the prior's region), and the parameter covariance of the run's last
    least-squares fit (``predict``'s sx, sy, sz)."""
    work = StageWork(run, "finish")
    rows = torch.cat([run.train.q, run.hold.q]) if run.options.refits else run.train.q
    fade = METHOD_TABLE[run.options.method].fades
    if run.prior is not None:  # the prior run's region stays calibrated, its learned corrections fade as they did
        if run.prior.model.region is not None:
            rows = torch.cat([rows, run.prior.model.region.to(rows)])
        fade = run.prior.model.region_fade
    work.model.set_region(rows, fade=fade)
    work.covariance = _covariance(run)
    return work.result()


def _covariance(run: CalibrationRun) -> ParameterCovariance | None:
    """The parameter covariance of the run's last least-squares fit, for the parameters the final model has (a
    later stage works on a copy of the model: the names are the same)."""
    if not run.fits:
        return None
    last = run.fits[-1]
    cov = fit_covariance(last)
    params = dict(run.model.named_parameters())
    if cov is None or any(n not in params for n in cov.names):
        return None
    return cov


@dataclass(frozen=True)
class MethodStages:
    """A calibration method: its stages in order, and how its model behaves beyond the calibrated region."""

    name: Method
    stages: tuple[StageFn, ...]
    #: the learned corrections fade to geometry beyond the region: the methods that add them to a geometry fitted
    #: alone (the integrated method's own gates fade its filters, whose geometry may only be right with their network)
    fades: bool
    trajectory_only: bool = False


#: the methods (``Options.method`` names one; tests/pipeline/test_state.py checks both lists agree)
METHOD_TABLE: dict[Method, MethodStages] = {
    m.name: m
    for m in (
        MethodStages(Method.AUTO, (nominal, geometric, closed_loop, learned, guard, finish), fades=True),
        MethodStages(Method.KINEMATIC, (nominal, geometric, refit_kinematic, finish), fades=False),
        MethodStages(Method.PCM, (nominal, nominal_geometry, correction_net_stage, finish), fades=True),
        MethodStages(Method.KINEMATIC_ANN, (nominal, geometric, correction_net_stage, finish), fades=True),
        MethodStages(
            Method.INTEGRATED, (nominal, geometric, integrated_stage, finish), fades=False, trajectory_only=True
        ),
    )
}

#: a calibration from a prior run (``calibrate(..., prior=)``): the kinematic method, started from the prior's model
#: and fitted about it (MAP), then what moved
PRIOR_METHOD = MethodStages(
    Method.KINEMATIC, (prior_start, prior_geometric, prior_refit, prior_moved, finish), fades=False
)
