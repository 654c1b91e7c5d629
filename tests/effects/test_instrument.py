"""The instrument's own errors (effects.instrument.TrackerError): known answers in the tracker's spherical
coordinates, derivatives, a run directory round trip, and the closed loop naming them on a campaign of several
stations."""

import math

import pytest
import torch

import torchcal
from torchcal.effects import Context, MeasurementModel, TrackerError, effect_from_config
from torchcal.errors import OptionError

F64 = torch.float64


def test_each_term_moves_the_point_along_its_own_spherical_direction():
    p = torch.tensor([[2.0, 0.0, 0.0], [0.0, 3.0, 0.0], [1.0, 1.0, math.sqrt(2.0)]], dtype=F64)
    az = TrackerError("azimuth", (1,), a=[0.0], b=[1e-5])  # d_az = 1e-5 cos(az)
    dp = az(None, Context(q=torch.zeros(3, 6, dtype=F64)), p_tracker=p).detach()
    assert torch.allclose(dp[0], torch.tensor([0.0, 2e-5, 0.0], dtype=F64), atol=1e-18)  # az 0: +y by 1e-5 * 2 m
    assert torch.allclose(dp[1], torch.zeros(3, dtype=F64), atol=1e-18)  # az 90 deg: cos = 0
    el = TrackerError("elevation", (1,), a=[2e-5], b=[0.0])  # d_el = 2e-5 sin(el)
    dp = el(None, Context(q=torch.zeros(3, 6, dtype=F64)), p_tracker=p).detach()
    assert torch.allclose(dp[0], torch.zeros(3, dtype=F64), atol=1e-18)  # el 0
    # el 45 deg, az 45 deg, rho 2: 2e-5 sin(45) * 2 along (-sin el cos az, -sin el sin az, cos el)
    d = 2e-5 * math.sin(math.pi / 4) * 2.0
    want = torch.tensor([-0.5 * d, -0.5 * d, math.cos(math.pi / 4) * d], dtype=F64)
    assert torch.allclose(dp[2], want, atol=1e-18)
    rng = TrackerError("range", c=[1e-5, 2e-6])  # 10 um + 2 ppm
    dp = rng(None, Context(q=torch.zeros(3, 6, dtype=F64)), p_tracker=p).detach()
    assert torch.allclose(dp.norm(dim=-1), 1e-5 + 2e-6 * p.norm(dim=-1), atol=1e-18)
    assert torch.allclose(torch.linalg.cross(dp, p), torch.zeros(3, 3, dtype=F64), atol=1e-18)  # along the line
    ctx = Context(q=torch.zeros(3, 6, dtype=F64))
    r2 = math.sqrt(2.0)
    # trunnion-axis tilt: d_az = t0 tan(el), 0 at el 0; at el 45 deg 1e-5 times rho_xy = sqrt 2 along e_az
    dp = TrackerError("tilt", t=[1e-5, 0.0])(None, ctx, p_tracker=p).detach()
    assert torch.allclose(dp[0], torch.zeros(3, dtype=F64), atol=1e-18)
    assert torch.allclose(dp[2], torch.tensor([-1e-5, 1e-5, 0.0], dtype=F64), atol=1e-18)
    # beam tilt (collimation): d_az = t1 / cos(el), so t1 rho along e_az
    dp = TrackerError("tilt", t=[0.0, 1e-5])(None, ctx, p_tracker=p).detach()
    assert torch.allclose(dp[0], torch.tensor([0.0, 2e-5, 0.0], dtype=F64), atol=1e-18)
    assert torch.allclose(dp[2], torch.tensor([-r2 * 1e-5, r2 * 1e-5, 0.0], dtype=F64), atol=1e-18)
    # beam offset: a constant displacement across the beam, turning with the head
    dp = TrackerError("beam", e=[1e-5, 2e-5])(None, ctx, p_tracker=p).detach()
    assert torch.allclose(dp[0], torch.tensor([0.0, 1e-5, 2e-5], dtype=F64), atol=1e-18)
    assert torch.allclose(dp.norm(dim=-1), torch.full((3,), math.sqrt(5) * 1e-5, dtype=F64), atol=1e-18)
    assert torch.allclose((dp * p).sum(-1), torch.zeros(3, dtype=F64), atol=1e-18)  # across the beam
    with pytest.raises(OptionError, match="azimuth, elevation, range, tilt, beam"):
        TrackerError("roll")
    with pytest.raises(OptionError, match="distinct positive"):
        TrackerError("azimuth", (0, 1))


def test_the_model_applies_it_in_the_tracker_frame_and_differentiates_it():
    robot = torchcal.load_robot("ur5")
    q = torch.rand(8, 6, generator=torch.Generator().manual_seed(0), dtype=F64)
    with torch.no_grad():
        robot.instrument.set_matrix(torch.tensor([[0.0, -1, 0, 1.5], [1, 0, 0, 0.2], [0, 0, 1, -0.3], [0, 0, 0, 1]]))
    eff = TrackerError("azimuth", (1, 2), a=[1e-5, -2e-5], b=[3e-5, 0.0])
    model = MeasurementModel(robot, [eff])
    ctx = Context(q=q)
    with torch.no_grad():
        p0 = MeasurementModel(robot)(ctx)
        assert torch.allclose(model(ctx) - p0, eff(robot, ctx, p_tracker=p0), atol=1e-15)

    def f(a):
        return torch.func.functional_call(model, {"effects.0.a": a}, (ctx,))

    J = torch.func.jacfwd(f)(eff.a.detach().clone())
    h = 1e-7
    for k in range(2):
        e = torch.zeros(2, dtype=F64)
        e[k] = h
        fd = (f(eff.a.detach() + e) - f(eff.a.detach() - e)) / (2 * h)
        assert torch.allclose(J[..., k], fd.detach(), atol=1e-9)


def test_a_tracker_error_rebuilds_from_its_config_and_state():
    for eff in (TrackerError("elevation", (3,), a=[1e-5], b=[2e-5]), TrackerError("range", c=[1e-5, 3e-6])):
        back = effect_from_config({"class": "TrackerError", **eff.config()})
        back.load_state_dict(eff.state_dict())
        assert back.describe() == eff.describe() and back.label() == eff.label()
    assert TrackerError("range").label() == "instrument(range offset and scale)"
    off = TrackerError("range", c=[2e-5], scale=False)
    back = effect_from_config({"class": "TrackerError", **off.config()})
    back.load_state_dict(off.state_dict())
    assert back.describe() == {"term": "range", "offset_m": 2e-5} and back.label() == "instrument(range offset)"
    for eff in (TrackerError("tilt", t=[1e-5, 2e-5]), TrackerError("beam", e=[1e-5, -3e-5])):
        back = effect_from_config({"class": "TrackerError", **eff.config()})
        back.load_state_dict(eff.state_dict())
        assert back.describe() == eff.describe() and back.label() == eff.label()


@pytest.mark.slow
def test_the_loop_names_an_azimuth_harmonic_on_three_stations_and_the_run_reloads(tmp_path):
    """One instrument re-stationed twice: its azimuth encoder's harmonic moves with it and not with the arm, so the
    data tell it from the geometry; the default method names it and its run directory predicts the same."""
    from torchcal.pipeline import Options, calibrate
    from torchcal.report.rundir import write_run
    from torchcal.sim import EffectSpec, SimConfig, simulate
    from torchcal.use.rundir import load_model

    spec = EffectSpec.parse("tracker_az:1=100urad")
    c = simulate(SimConfig(robot="ur5", poses=300, test_poses=30, seed=1, stations=3, effects=[spec]))
    run = calibrate("ur5", c.train, Options.of(seed=1))
    assert [e["name"] for e in run.effects_report] == ["instrument:azimuth:1"], run.effects_report
    model, _ = load_model(write_run(run, tmp_path / "run"))
    ctx = Context.from_measurements(c.test, trajectory=False)
    with torch.no_grad():
        assert torch.allclose(model(ctx), run.model(ctx), atol=1e-12)


def test_the_instrument_terms_are_offered_where_the_data_can_tell_them():
    """One station seeing the arm over 40 degrees of azimuth: not offered, with the reason; three stations: offered;
    one station whose points surround it (a span of 90 degrees or more): offered."""
    from torchcal.diagnose.candidates import MIN_AZIMUTH_SPAN, candidates
    from torchcal.sim import SimConfig, simulate

    for stations, offered in ((1, False), (3, True)):
        c = simulate(SimConfig(robot="ur5", poses=60, test_poses=0, seed=1, stations=stations))
        cands, skipped = candidates(c.model.robot, Context.from_measurements(c.train, trajectory=False))
        names = {x.name for x in cands}
        want = {f"instrument:{t}:{k}" for t in ("azimuth", "elevation") for k in range(1, 9)}
        want |= {"instrument:range", "instrument:tilt", "instrument:beam"}
        assert (want <= names) == offered and not any(n.startswith("instrument") for n in names - want)
        reasons = {s["name"]: s["reason"] for s in skipped}
        assert offered or "several stations or a wider span" in reasons["instrument:azimuth"]
        assert reasons["instrument:scale"].startswith("held at zero")
    # the instrument amid the arm's points: the same campaign's robot placed at the tracker's origin
    robot = c.model.robot
    one = torchcal.load_robot("ur5")
    with torch.no_grad():
        one.instrument.set_matrix(torch.eye(4, dtype=F64))
    q = c.train.q
    with torch.no_grad():
        p = MeasurementModel(one)(Context(q=q))
    span = torch.atan2(p[:, 1], p[:, 0])
    assert float(span.max() - span.min()) > MIN_AZIMUTH_SPAN
    names = {x.name for x in candidates(one, Context(q=q))[0]}
    assert "instrument:azimuth:3" in names and robot.stations


def _instrument_scores(effects: list[str], seed: int = 3):
    """The score tests of the instrument candidates at the kinematic fit of a three-station UR5 campaign of 200
    poses with ``effects``: best first."""
    from torchcal.diagnose.candidates import candidates
    from torchcal.diagnose.score import score_candidates
    from torchcal.pipeline import Options, calibrate
    from torchcal.sim import EffectSpec, SimConfig, simulate

    c = simulate(
        SimConfig(
            robot="ur5", poses=200, test_poses=0, seed=seed, stations=3, effects=[EffectSpec.parse(e) for e in effects]
        )
    )
    run = calibrate("ur5", c.train, Options.of(method="kinematic", seed=0))
    fit, train = run.fits[-1], c.train.subset(run.train_idx)
    ctx = Context.from_measurements(train, trajectory=False)
    cands, _ = candidates(run.model.robot, ctx)
    return score_candidates(run.model, fit.result, ctx, train.p, fit.whitening, cands=cands)


@pytest.mark.parametrize(
    "effect, name",
    [
        ("tracker_az:5=60urad", "instrument:azimuth:5"),
        ("tracker_el:3=60urad", "instrument:elevation:3"),
        ("axis_tilt=60urad", "instrument:tilt"),
        ("beam_offset=50um", "instrument:beam"),
    ],
)
def test_each_instrument_term_scores_first_where_it_is_injected(effect, name):
    """Over the whole menu (the couplings, the harmonics 1-8 of either encoder, with their multiple-testing
    correction), the injected term, and its harmonic, is the most significant candidate. (A beam tilt of 60 urad
    moves the point along the azimuth by ``t rho`` where a turn of the instrument moves it by ``t rho cos(el)``: over
    the arm's few tens of degrees of elevation 200 poses do not tell it; scripts/instrument_effects.py measures it on
    800.)"""
    best = _instrument_scores([effect])[0]
    assert best.candidate.name == name and best.significant(0.05), (best.candidate.name, best.p_bonferroni)


def test_no_instrument_term_is_significant_on_a_clean_campaign():
    scores = _instrument_scores([])
    assert not [s.candidate.name for s in scores if s.significant(0.05)]


def _two_instruments(split: bool):
    """A three-station UR5 campaign of 200 poses whose tracker has an azimuth harmonic 2 of 60 urad; with ``split``,
    station S3 was measured by another tracker whose harmonic has the opposite sign. Returns the kinematic run with
    the harmonic fitted jointly, its fit and its training data."""
    import copy
    import dataclasses

    from torchcal.estimate.fit import GEOMETRIC_GROUPS, solve
    from torchcal.pipeline import Options, calibrate
    from torchcal.sim import EffectSpec, SimConfig, simulate

    c = simulate(
        SimConfig(
            robot="ur5", poses=200, test_poses=0, seed=5, stations=3, effects=[EffectSpec.parse("tracker_az:2=60urad")]
        )
    )
    data = c.train
    if split:
        other = copy.deepcopy(c.model)
        with torch.no_grad():
            other.effects[0].a.neg_()
            other.effects[0].b.neg_()
            ctx = Context.from_measurements(data, trajectory=False)
            move = (other(ctx) - c.model(ctx)) * (data.station == data.station_names.index("S3")).unsqueeze(-1)
        data = dataclasses.replace(data, p=data.p + move)
    run = calibrate("ur5", data, Options.of(method="kinematic", seed=0))
    train = data.subset(run.train_idx)
    model = copy.deepcopy(run.model)
    model.add(TrackerError("azimuth", (2,)))
    fit = solve(
        model,
        train,
        GEOMETRIC_GROUPS,
        run.options.fit,
        "t",
        trajectory=False,
        effects=True,
        identifiability=run.identifiability,
    )
    return model, fit, train


@pytest.mark.parametrize("split", [False, True])
def test_a_station_whose_instrument_differs_is_named(split):
    """One tracker re-stationed: no station differs from the shared fit; a second tracker at S3 (its harmonic
    reversed): S3 differs (diagnose.stations)."""
    from torchcal.diagnose.stations import station_consistency

    model, fit, train = _two_instruments(split)
    ctx = Context.from_measurements(train, trajectory=False)
    tests = station_consistency(model, fit.result, ctx, train.p, fit.whitening, train.station_names, alpha=0.05)
    assert len(tests) == 3 and all(t["dof"] == 2 for t in tests)
    differs = sorted(t["station"] for t in tests if t["differs"])
    assert ("S3" in differs) if split else differs == [], tests


def test_simulate_takes_the_tilts_and_the_beam_offset_by_value_or_size():
    from torchcal.sim import EffectSpec, SimConfig, simulate

    spec = EffectSpec.parse("axis_tilt=40urad")
    assert (spec.kind, spec.variable, spec.amount) == ("axis_tilt", "tilt", pytest.approx(4e-5))
    assert EffectSpec.parse("beam_tilt=20urad").amount == pytest.approx(2e-5)
    assert EffectSpec.parse("beam_offset=30um").size == pytest.approx(3e-5)
    with pytest.raises(OptionError, match="urad or a length"):
        EffectSpec.parse("axis_tilt=5ppm")
    with pytest.raises(OptionError, match="takes no joint or order"):
        EffectSpec.parse("beam_offset:2=30um")
    c = simulate(
        SimConfig(
            robot="ur5",
            poses=40,
            test_poses=0,
            seed=2,
            stations=2,
            effects=[EffectSpec.parse(e) for e in ("axis_tilt=40urad", "beam_offset=30um", "tracker_el:5=20urad")],
        )
    )
    tilt, beam, el = c.truth["effects"]
    assert tilt["params"] == {"term": "tilt", "trunnion_rad": pytest.approx(4e-5), "beam_rad": 0.0}
    assert math.hypot(beam["params"]["azimuth_m"], beam["params"]["elevation_m"]) == pytest.approx(3e-5)
    assert beam["size_m"] == pytest.approx(3e-5) and el["order"] == 5 and "order" not in tilt


def test_an_encoder_order_the_data_hardly_part_from_its_neighbours_is_named_a_guess():
    """The orders whose score statistic lies within 2 ln 20 of the accepted order's are listed (the same encoder's,
    identifiable ones); another encoder's, another kind's and a far one's are not."""
    from types import SimpleNamespace

    from torchcal.diagnose.candidates import Candidate
    from torchcal.pipeline.loop import ALIKE_CHI2, _alike_orders

    def score(c, stat, ok=True):
        return SimpleNamespace(candidate=c, statistic=stat, identifiable=ok)

    el = {k: Candidate("instrument", None, "elevation", order=k) for k in range(1, 9)}
    az3 = Candidate("instrument", None, "azimuth", order=3)
    scores = [score(el[4], 307.8), score(el[5], 306.4), score(el[3], 306.0), score(el[2], 300.0)]
    scores += [score(el[6], 307.0, ok=False), score(az3, 307.5), score(Candidate("cyclic", 2), 307.7)]
    diag = SimpleNamespace(rounds=[{"scores": scores}])
    assert ALIKE_CHI2 == pytest.approx(5.99, abs=0.01)
    assert _alike_orders(el[4], diag) == ["instrument:elevation:5", "instrument:elevation:3"]
    assert _alike_orders(Candidate("instrument", None, "range"), diag) == []
