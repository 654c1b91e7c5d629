"""Localisation of residual structure (torchcal.diagnose.localise) and form selection on fitted campaigns.

Campaigns come from torchcal.sim.outside (effects written as formulas, outside the effect library) and,
where the folder exists, from the independent simulator's campaigns in TORCHCAL_OUTSIDE_DATA
(default ../shared/data/outside relative to the repository).
"""

from __future__ import annotations

import copy
import json
import math
import os
from pathlib import Path

import pytest
import torch

from torchcal.data import read_measurements
from torchcal.diagnose.forms import identify_form
from torchcal.diagnose.localise import (
    Variable,
    Workspace,
    candidate_variables,
    family_wise_p,
    localise,
    localise_variable,
    unexplained,
    workspace,
)
from torchcal.effects import Context
from torchcal.errors import OptionError
from torchcal.sim.campaign import SimConfig
from torchcal.sim.outside import OutsideEffect, simulate_outside

F64 = torch.float64
REPO = Path(__file__).resolve().parents[2]
OUTSIDE = Path(os.environ.get("TORCHCAL_OUTSIDE_DATA", REPO.parent / "shared" / "data" / "outside"))
ALPHA = 0.01


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


# --------------------------------------------------------------------------- the one place that fits geometry
def geometric_fit(train):
    """Kinematic calibration on (nearly) all of ``train``; returns what localisation and a refit need."""
    from torchcal.pipeline import Options, calibrate

    opts = Options.of(method="kinematic", holdout=0.01)
    run = calibrate("ur5", train, opts)
    tr = train.subset(run.train_idx)
    ctx = Context.from_measurements(tr, trajectory=False)
    fit = run.fits[-1]
    with torch.no_grad():
        r = tr.p - run.model(ctx)
    return {
        "run": run,
        "opts": opts,
        "train": tr,
        "ctx": ctx,
        "r": r,
        "W": fit.whitening,
        "J": fit.result.jacobian,
        "fit": fit,
    }


def joint_refit_rmse(g, effect, test) -> float:
    """Geometry + ``effect`` fitted jointly (the existing solve), held-out RMSE on ``test`` [m]."""
    from torchcal.estimate.fit import errors, solve
    from torchcal.stats import rmse

    model = copy.deepcopy(g["run"].model)
    model.add(effect)
    solve(
        model,
        g["train"],
        ("geometry", "instrument", "tool"),
        g["opts"].fit,
        "joint",
        trajectory=False,
        effects=True,
        identifiability=g["fit"].identifiability,
    )
    return rmse(errors(model, test, False))


def geometric_rmse(g, test) -> float:
    from torchcal.estimate.fit import errors
    from torchcal.stats import rmse

    return rmse(errors(g["run"].model, test, False))


def localise_fit(g):
    ws = workspace(g["run"].model, g["ctx"], g["r"], W=g["W"], jacobian=g["J"])
    return localise(g["run"].model, g["ctx"], ws), ws


# ------------------------------------------------------------------------ simulated beyond the library
CASES = {
    "harmonic3-wrist6": ([OutsideEffect("harmonic", joint=6, order=3, size=3e-5)], "q6", ("cyclic", [3])),
    "harmonic4-base1": ([OutsideEffect("harmonic", joint=1, order=4, size=3e-5)], "q1", ("cyclic", [4])),
    "harmonic5-wrist4": ([OutsideEffect("harmonic", joint=4, order=5, size=3e-5)], "q4", ("cyclic", [5])),
    "harmonic8-wrist5": ([OutsideEffect("harmonic", joint=5, order=8, size=3e-5)], "q5", ("cyclic", [8])),
    "harmonic8-base1": ([OutsideEffect("harmonic", joint=1, order=8, size=3e-5)], "q1", ("cyclic", [8])),
    "polynomial-shoulder2": (
        [OutsideEffect("polynomial", joint=2, coeffs=(1.0,), size=3e-5)],
        "q2",
        ("transmission", 1),
    ),
    "warmup-horizontal": (
        [OutsideEffect("warmup", axis="horizontal", tau=1800.0, size=3e-5)],
        "t",
        ("drift", "exponential"),
    ),
    "warmup-z": ([OutsideEffect("warmup", axis=2, tau=2700.0, size=3e-5)], "t", ("drift", "exponential")),
}


@pytest.mark.parametrize("name", list(CASES))
def test_localises_and_identifies_forms_beyond_the_library(name):
    effects, variable, (kind, order) = CASES[name]
    seed = 1 + list(CASES).index(name)
    c = simulate_outside(effects, SimConfig(poses=800, test_poses=200, seed=seed))
    g = geometric_fit(c.train)
    locs, ws = localise_fit(g)
    assert locs[0].name == variable, [(loc.name, loc.log10_p) for loc in locs[:4]]
    assert locs[0].significant(ALPHA)
    fc = identify_form(ws, locs[0].variable)
    assert fc.kind == kind, fc.to_dict()["bic_table"][:3]
    truth = c.truth["effects"][0]
    if kind == "drift":
        assert fc.form == order
        assert abs(fc.best.tau - truth["tau_s"]) < 2 * fc.best.tau_sigma, (fc.best.tau, fc.best.tau_sigma)
    else:
        assert fc.order == order
        assert fc.effect(g["run"].model).joint == truth["joint"]
    if kind == "cyclic":  # the amplitude of the harmonic within 3 sigma
        p = fc.params()
        k = order[0]
        for name_, true in ((f"a{k}", truth["a_sin"]), (f"b{k}", truth["b_cos"])):
            assert abs(p[name_]["value"] - true) < 3 * p[name_]["sigma"] + 0.05 * truth["amplitude_rad"]


def test_clean_campaign_names_nothing():
    c = simulate_outside([], SimConfig(poses=800, test_poses=200, seed=42))
    g = geometric_fit(c.train)
    locs, _ = localise_fit(g)
    assert len(locs) >= 20  # 6 joints x (angle, torque, flank) less the immobile ones, t, temperature, x, y, z
    assert family_wise_p(locs) > ALPHA, [(loc.name, loc.p_bonferroni) for loc in locs[:3]]


def test_localise_reports_its_smooth():
    c = simulate_outside(
        [OutsideEffect("harmonic", joint=3, order=6, size=3e-5)], SimConfig(poses=800, test_poses=0, seed=7)
    )
    g = geometric_fit(c.train)
    locs, _ = localise_fit(g)
    top = locs[0]
    assert top.name == "q3" and 0.3 < top.share <= 1.0 and top.edf > 1.0
    assert top.smooth.shape == top.grid.shape == top.smooth_se.shape
    # the shape's standard error (the smooth less its mean): here, with the level determined, about the pointwise one
    assert top.smooth_se_shape.shape == top.smooth.shape
    assert float(top.smooth_se_shape.mean()) == pytest.approx(float(top.smooth_se.mean()), rel=0.1)
    d = top.to_dict(with_smooth=True)
    assert d["variable"] == "q3" and len(d["smooth"]) == len(d["grid"])
    cart = next(loc for loc in locs if loc.name == "t")
    assert cart.smooth.shape == (len(cart.grid), 3)
    # the smooth follows the injected harmonic's shape where the data are (correlation of the curves)
    truth = c.truth["effects"][0]
    true_f = truth["amplitude_rad"] * torch.sin(6 * top.grid + truth["phase"])
    f = top.smooth - top.smooth.mean()
    assert float(torch.corrcoef(torch.stack([f, true_f]))[0, 1]) > 0.9


def test_the_test_holds_its_level_on_noise():
    """Pure noise through a Fourier smooth: the rate of p < 0.05 stays near 0.05 (GCV selection included)."""
    g = torch.Generator().manual_seed(3)
    n = 400
    q = (torch.rand(n, generator=g, dtype=F64) - 0.5) * 6.0
    coef = torch.randn(n, 3, generator=g, dtype=F64) * 0.5
    var = Variable("q1", "q1 [rad]", "joint", "fourier", q, 1, coef)
    hits = 0
    trials = 200
    for _ in range(trials):
        r = torch.randn(n, 3, generator=g, dtype=F64)
        ws = Workspace(r, sigma=1.0, joint_coefs=coef[:, :, None])
        hits += localise_variable(ws, var).p_value < 0.05
    assert hits / trials < 0.10


def test_candidate_variables_cover_joints_time_and_position():
    c = simulate_outside([], SimConfig(poses=60, test_poses=0, seed=5))
    g = geometric_fit(c.train)
    names = {v.name for v in candidate_variables(g["run"].model, g["ctx"])}
    assert {"q1", "q6", "tau2", "flank3", "t", "temperature", "x", "y", "z"} <= names
    # the UR5's joints 1 and 6 carry gravity torques of round-off size: the sign of such a torque is arithmetic
    # noise (it changed with the BLAS kernels), so neither a torque nor a flank variable is offered for them
    assert not {"tau1", "tau6", "flank1", "flank6"} & names


# -------------------------------------------------------------------------------- the outside campaigns
def _outside(name):
    folder = OUTSIDE / name
    if not (folder / "train.csv").exists():
        pytest.skip(f"outside campaign {folder} is absent (set TORCHCAL_OUTSIDE_DATA to the folder of campaigns)")
    index = {e["dir"]: e for e in json.loads((OUTSIDE / "index.json").read_text())}
    truth = json.loads((folder / "truth.json").read_text())["effect"]
    return read_measurements(folder / "train.csv"), read_measurements(folder / "test.csv"), truth, index[name]


@pytest.mark.parametrize("name", ["cyclic-s808", "cyclic_hi-s404", "warmup-s404", "jointscale-s404", "drift-s808"])
def test_outside_campaigns_localised_identified_and_held_out(name):
    train, test, truth, ref = _outside(name)
    g = geometric_fit(train)
    locs, ws = localise_fit(g)
    fc = identify_form(ws, locs[0].variable)
    ((family, t),) = truth.items()
    if family == "cyclic":
        assert locs[0].name == f"q{t['joint']}"
        assert fc.kind == "cyclic" and fc.order == [t["harmonic"]]
        a = math.hypot(fc.params()[f"a{t['harmonic']}"]["value"], fc.params()[f"b{t['harmonic']}"]["value"])
        assert abs(a - t["amp_rad"]) < 0.1 * t["amp_rad"]
    elif family == "jointscale":
        assert locs[0].name == f"q{t['joint']}"
        assert fc.kind == "transmission" and fc.order == 1
        c1 = fc.params()["c1"]
        assert abs(c1["value"] - t["k"]) < 3 * c1["sigma"] + 0.02 * abs(t["k"])
    else:
        assert locs[0].name == "t"
        assert fc.kind == "drift" and fc.form == "exponential"
        assert abs(fc.best.tau - t["tau_s"]) < 2 * fc.best.tau_sigma
    assert locs[0].significant(ALPHA)
    rmse = joint_refit_rmse(g, fc.effect(g["run"].model), test)
    assert rmse <= 1.2 * ref["rmse_oracle_mm"] * 1e-3, (rmse * 1e3, ref["rmse_oracle_mm"])
    assert rmse < geometric_rmse(g, test)


def test_outside_clean_campaign_names_nothing():
    train, _, truth, _ = _outside("none-s808")
    assert not truth
    g = geometric_fit(train)
    locs, _ = localise_fit(g)
    assert family_wise_p(locs) > ALPHA


def test_combination_localises_both_variables():
    effects = [
        OutsideEffect("harmonic", joint=5, order=6, size=3e-5),
        OutsideEffect("warmup", axis=2, tau=1200.0, size=3e-5),
    ]
    c = simulate_outside(effects, SimConfig(poses=800, test_poses=0, seed=21))
    g = geometric_fit(c.train)
    locs, _ = localise_fit(g)
    assert {loc.name for loc in locs[:2]} == {"q5", "t"}
    assert all(loc.significant(ALPHA) for loc in locs[:2])
    left = unexplained(locs, ALPHA)
    assert [d["variable"] for d in left[:2]] == [loc.name for loc in locs[:2]]
    assert all(d["share"] > 0 and len(d["smooth"]) == len(d["grid"]) for d in left)


def test_outside_generator_trajectory_and_truth():
    cfg = SimConfig(trajectory=True, samples=400, train_samples=300, seed=4)
    c = simulate_outside([OutsideEffect("polynomial", joint=3, coeffs=(1.0, 0.5), size=2e-5)], cfg)
    assert c.train.n == 300 and c.test.n == 100
    assert bool((torch.diff(c.train.t) > 0).all())
    e = c.truth["effects"][0]
    assert e["form"] == "polynomial" and e["degree"] == 2 and e["coeffs"][1] == pytest.approx(0.5 * e["coeffs"][0])
    ctx = Context.from_measurements(c.train, trajectory=True)
    variables = candidate_variables(c.model, ctx)
    flanks = [v for v in variables if v.name.startswith("flank")]
    assert flanks and all("motion direction" in v.label for v in flanks)
    assert "q3" in {v.name for v in variables}
    with pytest.raises(OptionError, match="joint"):
        OutsideEffect("harmonic", order=3)
