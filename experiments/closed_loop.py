"""Simulate-and-check for the closed loop: does it name the injected effects, and what does it reach?

One case = one simulated campaign (:mod:`torchcal.sim`) with known effects, calibrated with the
default ``auto`` method. The loop's held-out error is compared with

* ``geometric``: the geometric fit alone (the loop's own stage 1);
* ``true_form``: the model of exactly the injected named kinds (same joints, same variables),
  fitted jointly with the geometry on the same training poses, no search: what a user who knew
  the answer would fit (only for campaigns without a ``field``, which has no parametric form);
* ``oracle``: the true model of the simulation at the same poses (the noise floor).

Errors are RMS of the position error on the run's held-out poses and on the campaign's separate
test file (``test_*``).
"""

from __future__ import annotations

import copy
import time

from torchcal.diagnose.candidates import Candidate
from torchcal.effects.registry import NAMED_KINDS
from torchcal.estimate.fit import errors, solve
from torchcal.pipeline import Options, calibrate
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.stats import rmse
from torchcal.sweep import TaskFailure, map_tasks

NAMED = NAMED_KINDS


def truth_effects(truth: dict) -> list[tuple[str, int | None]]:
    """``(kind, joint)`` of the injected effects, as report.json names them (a field is ``learned``)."""
    return [(e["kind"], e["joint"]) for e in truth["effects"]]


def found_effects(run) -> list[tuple[str, int | None]]:
    return [(e["kind"], e["joint"]) for e in run.effects_report]


def truth_names(truth: dict) -> list[str]:
    """Injected effects as ``kind:joint`` / ``drift:variable`` / ``learned`` (a field)."""

    def name(e):
        if e["kind"] == "learned":
            return "learned"
        if e.get("source") is not None:  # a coupling, as the loop names it: joint <- source
            return f"{e['kind']}:{e['joint']}<-{e['source']}"
        if e["kind"] == "instrument":  # as the loop's candidates name them: term, and an encoder's harmonic
            return f"instrument:{_instrument_term(e)}" + (f":{e['order']}" if e.get("order") is not None else "")
        return f"{e['kind']}:{e['joint'] if e['joint'] is not None else e['variable']}"

    return [name(e) for e in truth["effects"]]


def _instrument_term(e: dict) -> str:
    """An injected instrument term's candidate variable: a range scale is ``scale`` (never offered: it is held)."""
    return "scale" if e.get("spec") == "range_scale" else e["variable"]


def found_names(run) -> list[str]:
    return [e.get("name", e["kind"]) for e in run.effects_report]


def true_form_candidates(truth: dict, reference: dict) -> list[Candidate] | None:
    """Candidates of exactly the injected named effects; None when a field (no parametric form) is injected."""
    out = []
    for e in truth["effects"]:
        if e["kind"] not in NAMED:
            return None
        var = _instrument_term(e) if e["kind"] == "instrument" else e.get("variable")
        ref = reference.get(var, 0.0) if var else 0.0
        out.append(Candidate(e["kind"], e["joint"], var, ref, source=e.get("source"), order=e.get("order")))
    return out


def run_case(
    robot: str = "ur5",
    effects: list[str] | tuple[str, ...] = (),
    *,
    poses: int = 800,
    test_poses: int = 200,
    seed: int = 0,
    trajectory: bool = False,
    samples: int = 3000,
    sigma_tracker: float = 15e-6,
    options: Options | None = None,
    load: dict | None = None,
    stations: int = 1,
) -> dict:
    """Simulate, calibrate with ``auto``, and compare (module docstring). Returns plain numbers [mm, s]. ``load``:
    a static campaign's load settings (:class:`~torchcal.sim.SimConfig`'s ``payload_levels``, ``torques``), so that
    the closed loop offers its load candidates; ``stations``: a static campaign's instrument placements (several
    tell the instrument's own errors from its pose and the geometry)."""
    specs = [EffectSpec.parse(e) for e in effects]
    if trajectory:
        cfg = SimConfig(
            robot=robot,
            trajectory=True,
            samples=samples,
            train_samples=int(round(0.8 * samples)),
            seed=seed,
            effects=specs,
            sigma_tracker=sigma_tracker,
        )
    else:
        cfg = SimConfig(
            robot=robot,
            poses=poses,
            test_poses=test_poses,
            seed=seed,
            effects=specs,
            sigma_tracker=sigma_tracker,
            stations=stations,
            **(load or {}),
        )
    c = simulate(cfg)
    opts = options or Options(seed=seed)
    t0 = time.perf_counter()
    run = calibrate(robot, c.train, opts)
    seconds = time.perf_counter() - t0
    train = c.train.subset(run.train_idx)
    hold = c.train.subset(run.holdout_idx)
    traj = run.trajectory
    geo = next(s for s in run.stages if s.name == "geometric")

    def both(model):
        return rmse(errors(model, hold, traj)) * 1e3, rmse(errors(model, c.test, traj)) * 1e3

    out = {
        "robot": robot,
        "effects": list(effects),
        "seed": seed,
        "trajectory": trajectory,
        "n_train": len(run.train_idx),
        "n_holdout": len(run.holdout_idx),
        "seconds": seconds,
        "truth": [list(t) for t in truth_effects(c.truth)],
        "found": [list(f) for f in found_effects(run)],
        "stages": [s.name for s in run.stages],
        "rejected": [r.get("name", r["kind"]) for r in run.rejected],
    }
    out["truth_names"], out["found_names"] = truth_names(c.truth), found_names(run)
    # an encoder harmonic's other orders the data hardly told from the one named (pipeline.loop._alike_orders)
    out["found_alike"] = [n for e in run.effects_report for n in e.get("evidence", {}).get("alike", [])]
    out["truth_rms_um"] = [e["size_m"] * 1e6 for e in c.truth["effects"]]  # each effect's RMS probe displacement
    out["correct"] = sorted(out["truth_names"]) == sorted(out["found_names"])
    out["loop_mm"], out["test_loop_mm"] = run.stages[-1].rmse * 1e3, rmse(errors(run.model, c.test, traj)) * 1e3
    out["geometric_mm"], out["test_geometric_mm"] = geo.rmse * 1e3, rmse(errors(geo.model, c.test, traj)) * 1e3
    out["oracle_mm"], out["test_oracle_mm"] = both(c.model)
    ref = {
        "t": float(train.t[0]) if train.t is not None else 0.0,
        "temperature": float(train.temperature[0]) if train.temperature is not None else 0.0,
    }
    cands = true_form_candidates(c.truth, ref)
    if cands is None or not cands:
        out["true_form_mm"], out["test_true_form_mm"] = (
            (out["geometric_mm"], out["test_geometric_mm"]) if cands == [] else (None, None)
        )
    else:
        model = copy.deepcopy(geo.model)
        for cand in cands:
            model.add(cand.make())
        ida = next((f.identifiability for f in run.fits if f.stage == "geometric"), None)
        solve(
            model,
            train,
            ("geometry", "instrument", "tool"),
            opts.fit,
            "true form",
            trajectory=traj,
            effects=True,
            identifiability=ida,
        )
        out["true_form_mm"], out["test_true_form_mm"] = both(model)
    return out


def _run_one(kw: dict) -> dict:
    """One case (a keyword dict of :func:`run_case`): a task of :func:`torchcal.sweep.map_tasks`."""
    return run_case(**kw)


def run_cases(cases: list[dict], workers: int | None = 1, progress=None, address: str | None = None) -> list[dict]:
    """:func:`run_case` for every keyword dict in ``cases``, in order; ``workers`` > 1 (a local Ray instance of
    that many CPUs) or ``address`` (a Ray cluster) runs them as independent tasks
    (:func:`torchcal.sweep.map_tasks`: the same results as one after another); ``progress`` sees each run's row
    as it ends."""

    def show(_i: int, r) -> None:
        if progress and not isinstance(r, TaskFailure):
            progress(r)

    return map_tasks(_run_one, cases, workers=workers, address=address, progress=show)
