"""After the closed loop, identifiability over effects and geometry together: a direction the final fit cannot
tell between an effect and the geometry is named (pipeline.loop.effect_trades), one it can is not."""

import copy

import pytest

from torchcal.effects import Coupling, Cyclic
from torchcal.estimate.fit import solve
from torchcal.pipeline import Options, calibrate
from torchcal.pipeline.loop import GROUPS, effect_trades
from torchcal.sim import EffectSpec, SimConfig, simulate


def _refit_with(run, train, effect):
    """The run's geometric model with ``effect`` added, fitted jointly on ``train`` as the closed loop fits it."""
    model = copy.deepcopy(run.model)
    model.add(effect)
    fit = solve(
        model,
        train,
        GROUPS,
        run.options.fit,
        "trial",
        trajectory=False,
        effects=True,
        identifiability=run.identifiability,
    )
    return model, fit


@pytest.fixture(scope="module")
def narrow_run():
    """A UR5 campaign whose joint 2 stays within a band of 4 degrees: its kinematic calibration."""
    c = simulate(SimConfig(robot="ur5", poses=150, test_poses=0, seed=4, narrow=(2,), narrow_width_deg=4.0))
    run = calibrate("ur5", c.train, Options.of(method="kinematic", seed=0))
    return run, c.train.subset(run.train_idx)


def test_a_cosine_harmonic_over_a_narrow_range_is_named_as_trading_with_the_joint_offset(narrow_run):
    """Over 4 degrees cos(q2) is a constant to 6e-4 of itself: the harmonic's cosine amplitude and the joint's offset
    (theta of joint 2) move together, and the data cannot tell them apart."""
    run, train = narrow_run
    model, fit = _refit_with(run, train, Cyclic(2, harmonics=(1,)))
    trades = effect_trades(model, fit)
    assert trades, "the cosine term and joint 2's offset must be named"
    t = trades[0]
    assert any(n.endswith(".b") or ".b[" in n for n in t["effects"]) and t["robot"], t
    assert any("theta" in n and "2" in n for n in t["robot"]), t["robot"]
    assert t["correlation"] > 0.999 and "cannot tell" in t["note"]


def test_a_coupling_the_data_determine_is_not_named(narrow_run):
    run, train = narrow_run
    model, fit = _refit_with(run, train, Coupling(5, 4))
    assert effect_trades(model, fit) == []


@pytest.mark.slow
def test_a_run_that_names_a_coupling_reports_no_trade():
    c = simulate(
        SimConfig(robot="ur5", poses=150, test_poses=0, seed=2, effects=[EffectSpec.parse("coupling:5<-4=2e-3")])
    )
    run = calibrate("ur5", c.train, Options.of(seed=0))
    assert [e.kind for e in run.model.effects] == ["coupling"]
    assert run.diagnosis.trades == [] and "trades" not in run.diagnosis.to_dict()


def test_a_trade_with_the_geometry_is_held_at_the_effects_zero(narrow_run):
    """Over 4 degrees the harmonic's cosine is joint 2's offset and its sine a bend the link lengths and offsets
    make: both amplitudes are held at zero and the model refitted; the trades are gone from the refit, the
    identifiability analysis names the held elements with their reason, and the fit is as good (the data could not
    tell them apart)."""
    from torchcal.estimate.fit import errors
    from torchcal.pipeline.effect_holds import hold_trades
    from torchcal.stats import rmse

    run, train = narrow_run
    model, fit = _refit_with(run, train, Cyclic(2, harmonics=(1,)))
    trades = effect_trades(model, fit)
    before = rmse(errors(model, train, False))
    held_fit, names = hold_trades(model, train, run.identifiability, trades, run.options.fit, trajectory=False)
    assert held_fit is not None and sorted(names) == ["cyclic(joint 2).a", "cyclic(joint 2).b"], names
    assert float(model.effects[-1].b.detach().abs().max()) == 0.0 == float(model.effects[-1].a.detach().abs().max())
    assert not set(names) & set(held_fit.result.names)
    assert effect_trades(model, held_fit) == []
    entry = next(f for f in held_fit.identifiability.fixed if f["name"] == "cyclic(joint 2).b")
    assert "held at the effect's zero" in entry["reason"] and any("theta" in d for d in entry["depends_on"])
    assert names[0] not in run.identifiability.names  # the run's own analysis is left as it was
    assert rmse(errors(model, train, False)) <= before * 1.001


@pytest.mark.slow
def test_the_closed_loop_holds_a_trade_and_reports_it(monkeypatch, tmp_path):
    """Through the loop, the run directory and report.json (the trade threshold lowered to 0.9 to see trades on 200
    poses): an azimuth harmonic 1 of 60 urad on three stations trades with the stations' positions at 0.998; its cosine
    amplitude, 7 sigma from zero, is kept and named, its sine amplitude, which the data do not tell from zero, is held
    there, named in the identifiability analysis with its reason, and its record and the note say so."""
    import functools
    import json

    import torchcal.pipeline.loop as L
    from torchcal.report.rundir import write_run

    monkeypatch.setattr(L, "effect_trades", functools.partial(effect_trades, max_correlation=0.9))
    c = simulate(
        SimConfig(
            robot="ur5", poses=200, test_poses=0, seed=3, stations=3, effects=[EffectSpec.parse("tracker_az:1=60urad")]
        )
    )
    run = calibrate("ur5", c.train, Options.of(seed=0))
    assert [e["name"] for e in run.effects_report] == ["instrument:azimuth:1"]
    t = run.diagnosis.trades[0]
    a, b = "instrument(azimuth harmonic 1).a", "instrument(azimuth harmonic 1).b"
    assert t["held"] == [a] and list(t["kept"]) == [b] and t["kept"][b] ** 2 > 10.828, t
    assert all(n.startswith("instrument[S") for n in t["robot"])
    assert any("held at the effect's zero" in n for n in run.notes)
    rep = json.loads((write_run(run, tmp_path / "run") / "report.json").read_text())
    fixed = {f["name"]: f["reason"] for f in rep["parameters"]["identifiability"]["fixed"]}
    assert "held at the effect's zero" in fixed[a] and b not in fixed
    params = rep["effects"][0]["params"]
    assert params["a"]["value"] == 0.0 and "held at zero" in params["a"]["note"] and params["b"]["value"] != 0.0
