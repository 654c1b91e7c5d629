"""Localise and identify one undeclared effect after a kinematic calibration; held-out RMSE of geometry + it.

For each campaign: kinematic calibration on the training file, localisation of the residual
(:func:`torchcal.diagnose.localise.localise`), form selection at the top variable
(:func:`torchcal.diagnose.forms.identify_form`), the chosen effect refitted jointly with the geometry, and the
held-out RMSE on the test file next to geometry alone and to the reference ``rmse_oracle_mm``: the outside
folder's index.json, or for the formula campaigns of :mod:`torchcal.sim.outside` the same refit with the true
form. Run by ``scripts/localise_outside.py``.
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import torch

from torchcal.data import read_measurements
from torchcal.diagnose.forms import identify_form
from torchcal.diagnose.localise import localise, workspace
from torchcal.effects import Context, Cyclic, Drift, Transmission
from torchcal.estimate.fit import errors, solve
from torchcal.pipeline import Options, calibrate
from torchcal.sim.campaign import SimConfig
from torchcal.sim.outside import OutsideEffect, simulate_outside
from torchcal.stats import rmse

SIMULATED = {
    "harmonic3-wrist6": [OutsideEffect("harmonic", joint=6, order=3, size=3e-5)],
    "harmonic4-base1": [OutsideEffect("harmonic", joint=1, order=4, size=3e-5)],
    "harmonic5-wrist4": [OutsideEffect("harmonic", joint=4, order=5, size=3e-5)],
    "harmonic8-wrist5": [OutsideEffect("harmonic", joint=5, order=8, size=3e-5)],
    "polynomial-shoulder2": [OutsideEffect("polynomial", joint=2, coeffs=(1.0,), size=3e-5)],
    "warmup-horizontal-10min": [OutsideEffect("warmup", axis="horizontal", tau=600.0, size=3e-5)],
    "warmup-z-45min": [OutsideEffect("warmup", axis=2, tau=2700.0, size=3e-5)],
}


def _refit(run, train, fit, opts, effect, test) -> float:
    model = copy.deepcopy(run.model)
    model.add(effect)
    solve(
        model,
        train,
        ("geometry", "instrument", "tool"),
        opts.fit,
        "joint",
        trajectory=False,
        effects=True,
        identifiability=fit.identifiability,
    )
    return rmse(errors(model, test, False))


def one(train, test, oracle_mm=None, true_effect=None) -> dict:
    t0 = time.perf_counter()
    opts = Options.of(method="kinematic", holdout=0.01)
    run = calibrate("ur5", train, opts)
    tr = train.subset(run.train_idx)
    ctx = Context.from_measurements(tr, trajectory=False)
    fit = run.fits[-1]
    with torch.no_grad():
        r = tr.p - run.model(ctx)
    t1 = time.perf_counter()
    ws = workspace(run.model, ctx, r, W=fit.whitening, jacobian=fit.result.jacobian)
    locs = localise(run.model, ctx, ws)
    fc = identify_form(ws, locs[0].variable)
    t2 = time.perf_counter()
    eff = fc.effect(run.model)
    out = {
        "top": [loc.to_dict() for loc in locs[:3]],
        "form": fc.to_dict(),
        "rmse_geometric_mm": rmse(errors(run.model, test, False)) * 1e3,
        "rmse_identified_mm": None if eff is None else _refit(run, tr, fit, opts, eff, test) * 1e3,
        "seconds_localise_and_form": t2 - t1,
    }
    if true_effect is not None:
        oracle_mm = _refit(run, tr, fit, opts, true_effect, test) * 1e3
    out["rmse_oracle_mm"] = oracle_mm
    if oracle_mm and out["rmse_identified_mm"]:
        out["ratio_to_oracle"] = out["rmse_identified_mm"] / oracle_mm
    out["seconds_total"] = time.perf_counter() - t0
    out["form"]["bic_table"] = out["form"]["bic_table"][:4]
    return out


def clean(n: int, seed: int, alpha: float = 0.01) -> dict:
    """Localisation on ``n`` campaigns without any effect: the smallest Bonferroni p of each."""
    ps = []
    for i in range(n):
        c = simulate_outside([], SimConfig(poses=800, test_poses=0, seed=seed + 1000 + i))
        run = calibrate("ur5", c.train, Options.of(method="kinematic", holdout=0.01))
        tr = c.train.subset(run.train_idx)
        ctx = Context.from_measurements(tr, trajectory=False)
        fit = run.fits[-1]
        with torch.no_grad():
            r = tr.p - run.model(ctx)
        locs = localise(run.model, ctx, workspace(run.model, ctx, r, W=fit.whitening, jacobian=fit.result.jacobian))
        ps.append({"seed": seed + 1000 + i, "top": locs[0].name, "p_bonferroni": locs[0].p_bonferroni})
    return {"runs": ps, "alpha": alpha, "false_positives": sum(p["p_bonferroni"] < alpha for p in ps), "n": n}


def true_form(truth: dict, t0: float):
    e = truth["effects"][0]
    if e["form"] == "harmonic":
        return Cyclic(e["joint"], harmonics=[e["order"]])
    if e["form"] == "polynomial":
        return Transmission(e["joint"], degree=e["degree"])
    return Drift("t", "instrument", reference=t0, form="exponential", tau=e["tau_s"])


def run(outside: Path | None, campaigns: list[str], simulated: bool, seed: int, n_clean: int) -> dict:
    """Localise and identify on the ``campaigns`` of the folder ``outside`` (if given), on the formula campaigns
    of :data:`SIMULATED` (if ``simulated``, seeded from ``seed``), and localise on ``n_clean`` clean campaigns.

    Returns:
        One entry per campaign (and ``clean``), as :func:`one` and :func:`clean` return them.
    """
    res = {}
    if outside:
        index = {e["dir"]: e for e in json.loads((outside / "index.json").read_text())}
        for name in campaigns:
            d = outside / name
            res[name] = one(
                read_measurements(d / "train.csv"),
                read_measurements(d / "test.csv"),
                index[name].get("rmse_oracle_mm"),
            )
    if simulated:
        for i, (name, effects) in enumerate(SIMULATED.items()):
            c = simulate_outside(effects, SimConfig(poses=800, test_poses=200, seed=seed + i))
            res[name] = one(c.train, c.test, true_effect=true_form(c.truth, float(c.train.t[0])))
            res[name]["truth"] = c.truth["effects"]
    if n_clean:
        res["clean"] = clean(n_clean, seed)
    return res
