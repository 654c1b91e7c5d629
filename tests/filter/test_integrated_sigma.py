"""The integrated method's predictive standard deviation (issue 12): the gate's variance, its coverage and scale
calibration, a saved gate rebuilt with it, predict's sx, sy, sz columns; and the rule that keeps geometry alone
unless a candidate beats it on the validation block with any one piece left out. All on small hand-built models
(seconds)."""

import copy
import json
import math

import pytest
import torch

from torchcal.cli import main
from torchcal.data import Measurements, read_measurements, write_measurements
from torchcal.effects import Context, LearnedEffect, MeasurementModel
from torchcal.effects.base import Effect
from torchcal.effects.predictive import GatedBlock, calibrate_predictive_sigma, sigma_check
from torchcal.effects.region import (
    RegionGate,
    calibrate_factor,
    coverage,
    fit_fallback_growth,
    fit_fallback_scale,
    fit_predictive_scale,
    predictive_sigma,
)
from torchcal.effects.registry import effect_from_config
from torchcal.filter.adaptive import random_features
from torchcal.pipeline import Options, calibrate
from torchcal.pipeline import integrated as I
from torchcal.pipeline.state import StageWork
from torchcal.robot import load_robot
from torchcal.sim import SimConfig, simulate

NOISE, FAR = 2e-5, 3e-4  # [m]


def _gate(length=1.0, scale=1.0, n=300, seed=0):
    """A UR5 with a random-feature correction behind a gate with a predictive standard deviation, and its region."""
    g = torch.Generator().manual_seed(seed)
    robot = load_robot("ur5")
    net = random_features(hidden=16, seed=seed)
    with torch.no_grad():
        net.fc2.weight.normal_(0.0, 0.1, generator=g)
    region = 0.3 * torch.randn(n, 6, generator=g, dtype=torch.float64)
    idx = torch.arange(net.hidden * 7, net.hidden * 7 + 3 * net.hidden)  # the output weights
    A = torch.randn(len(idx), len(idx), generator=g, dtype=torch.float64)
    gate = RegionGate(LearnedEffect(net), region, length)
    gate.set_predictive(
        1e-4 * A @ A.T / len(idx), idx, torch.full((3,), NOISE, dtype=torch.float64), torch.full((3,), FAR).double(),
        length if math.isfinite(length) else 8.0, scale,
    )  # fmt: skip
    return robot, gate, region


def test_coverage_and_the_calibrated_factor_recover_a_known_sigma():
    g = torch.Generator().manual_seed(1)
    sigma = torch.rand(4000, 3, generator=g, dtype=torch.float64) + 0.5
    e = sigma * torch.randn(4000, 3, generator=g, dtype=torch.float64)
    assert coverage(e, sigma) == pytest.approx(0.9545, abs=0.01)
    assert coverage(e, 0.5 * sigma) == pytest.approx(0.683, abs=0.015)
    # the model's sigma is half the truth: 95 % lie within 1.96 true sigmas, 3.92 of the model's, so s = 1.96
    s = calibrate_factor(e, (0.5 * sigma).square(), torch.zeros_like(e))  # no unscaled part
    assert s == pytest.approx(1.96, rel=0.05)
    assert coverage(e, s * 0.5 * sigma) >= 0.95
    with pytest.raises(ValueError, match="same non-empty shape"):
        coverage(e, sigma[:10])


def test_the_scale_and_floor_by_likelihood_hold_coverage_where_the_network_term_says_little():
    g = torch.Generator().manual_seed(2)
    n = 3000
    a = torch.full((n, 3), 1e-8, dtype=torch.float64)  # the filter's term: large and flat (mostly its prior)
    g2 = torch.rand(n, 1, generator=g, dtype=torch.float64).expand(n, 3).clone()  # some samples off the region
    b = (1.0 - g2) * (5e-5) ** 2  # the geometry's residual scale there
    truth = torch.tensor([2e-5, 3e-5, 1e-5], dtype=torch.float64)
    e = (g2 * truth**2 + b).sqrt() * torch.randn(n, 3, generator=g, dtype=torch.float64)
    scale, floor = fit_predictive_scale(e, a, b, g2)
    assert scale < 0.05  # the flat network term is not what explains the residuals
    torch.testing.assert_close(torch.tensor(floor, dtype=torch.float64), truth, rtol=0.15, atol=0.0)
    sigma = (scale**2 * a + g2 * torch.tensor(floor, dtype=torch.float64) ** 2 + b).sqrt()
    assert 0.945 <= coverage(e, sigma) <= 0.97
    with pytest.raises(ValueError, match="same non-empty shape"):
        fit_predictive_scale(e, a[:10], b, g2)


def test_the_calibrated_factor_is_exact_with_an_unscaled_far_part():
    g = torch.Generator().manual_seed(3)
    n = 5000
    near = (torch.rand(n, 3, generator=g, dtype=torch.float64) + 0.5) ** 2
    far = torch.rand(n, 3, generator=g, dtype=torch.float64) ** 2
    e = (4.0 * near + far).sqrt() * torch.randn(n, 3, generator=g, dtype=torch.float64)  # the truth: factor 2
    s = calibrate_factor(e, near, far)
    assert s == pytest.approx(2.0, rel=0.05)
    assert coverage(e, (s**2 * near + far).sqrt()) >= 0.95
    assert coverage(e, ((0.999 * s) ** 2 * near + far).sqrt()) < 0.95  # the smallest such factor
    # components no factor can cover (no near part, outside 2 sqrt(far)): the largest factor that covers the rest
    near[:400] = 0.0
    e[:400] = 10.0
    s = calibrate_factor(e, near, far)
    assert math.isfinite(s) and coverage(e[400:], (s**2 * near[400:] + far[400:]).sqrt()) == 1.0
    with pytest.raises(ValueError, match="same non-empty shape"):
        calibrate_factor(e, near[:10], far)


def test_a_factor_that_would_run_away_on_an_almost_closed_gate_is_capped():
    from torchcal.effects.region import FACTOR_SIGMA_RATIO

    g = torch.Generator().manual_seed(5)
    n = 2000
    near = (torch.rand(n, 3, generator=g, dtype=torch.float64) + 0.5) ** 2
    far = 0.01 * torch.ones(n, 3, dtype=torch.float64)
    e = near.sqrt() * torch.randn(n, 3, generator=g, dtype=torch.float64)
    # a tenth of the components where the gate is almost closed: a near part of 1e-40 and residuals beyond
    # 2 sqrt(far); covering them needs a factor of about 1e20, which would make every other sigma absurd
    near[:200] = 1e-40
    e[:200] = 1.0
    free = calibrate_factor(e, near, far, max_ratio=math.inf)
    assert free > 1e15
    s = calibrate_factor(e, near, far)
    sigma = (s**2 * near + far).sqrt()
    # the scaled near part's largest standard deviation is the cap times the largest residual (far is unscaled)
    assert s < free and float((s**2 * near).sqrt().max()) == pytest.approx(FACTOR_SIGMA_RATIO * float(e.abs().max()))
    assert coverage(e, sigma) < 0.95  # the target is then not reached, and the run's sigma check says so
    # a factor below the cap is unchanged by it
    ok = calibrate_factor(e[200:], near[200:], far[200:])
    assert ok == calibrate_factor(e[200:], near[200:], far[200:], max_ratio=math.inf)


def test_the_scale_with_held_out_residuals_is_widened_to_the_target_over_both_never_narrowed():
    g = torch.Generator().manual_seed(4)
    n = 3000
    a = torch.full((n, 3), 1e-10, dtype=torch.float64)
    g2 = torch.ones(n, 3, dtype=torch.float64)
    b = torch.zeros(n, 3, dtype=torch.float64)

    def draw(s):
        return s * torch.randn(n, 3, generator=g, dtype=torch.float64)

    e_val = draw(2e-5)
    scale0, floor0 = fit_predictive_scale(e_val, a, b, g2)
    # a held-out stretch easier than validation: the likelihood fit is kept, not narrowed
    assert fit_predictive_scale(e_val, a, b, g2, holdout=(draw(1e-5), a, b, g2)) == (scale0, floor0)
    # a harder one: widened until 95 % of both together lie within 2 sigma (to a component or two)
    e_hold = draw(6e-5)
    scale, floor = fit_predictive_scale(e_val, a, b, g2, holdout=(e_hold, a, b, g2))
    sigma = (scale**2 * a + g2 * torch.tensor(floor, dtype=torch.float64) ** 2 + b).sqrt()
    assert abs(coverage(torch.cat([e_val, e_hold]), torch.cat([sigma, sigma])) - 0.95) <= 2.0 / (6 * n)
    assert coverage(e_val, sigma) > 0.99 and coverage(e_hold, sigma) < 0.95  # each block alone: off the target
    # the factor acts on scale and floor together, from the same likelihood fit on validation
    assert floor[0] > floor0[0] and scale / scale0 == pytest.approx(floor[0] / floor0[0], rel=1e-9)
    with pytest.raises(ValueError, match="same non-empty"):
        fit_predictive_scale(e_val, a, b, g2, holdout=(e_val[:10], a, b, g2))


def test_sigma_is_the_filters_at_the_support_and_the_geometrys_far_from_it():
    robot, gate, region = _gate(scale=3.0)
    near = gate.predictive_std(robot, region[:50])
    assert near.shape == (50, 3) and bool((near > 3.0 * NOISE * 0.999).all())
    a, b, g2 = gate.variance_parts(robot, region[:50])
    assert float(b.abs().max()) < 1e-10 * FAR**2  # on the region the gate is 1 (to round-off): no fallback part
    torch.testing.assert_close(near, (9.0 * a + b).sqrt())  # the scale acts on the network's and noise's part
    gate.sigma_floor = [1e-5, 2e-5, 3e-5]
    floor = torch.tensor(gate.sigma_floor, dtype=torch.float64)
    torch.testing.assert_close(gate.predictive_std(robot, region[:50]), (9.0 * a + g2 * floor**2 + b).sqrt())
    # the output-weight Jacobian rotated into the tracker frame, through P: by hand for one sample
    net, q = gate.inner.net, region[:1]
    J = robot.T_tracker_base()[:3, :3] @ net.jacobian_flat(net.flat(), q)[1][0][:, gate.weight_index]
    var = (J @ gate.weight_cov @ J.T).diagonal() + NOISE**2
    torch.testing.assert_close(a[0], var)
    far = gate.predictive_std(robot, region[:5] + 20.0)  # many spreads away: the geometry's residual scale, unscaled
    torch.testing.assert_close(far, torch.full_like(far, FAR), rtol=1e-6, atol=0.0)


def test_the_fallbacks_growth_with_distance_is_recovered_and_zero_where_there_is_none():
    g = torch.Generator().manual_seed(3)
    n = 6000
    d = 4.0 * torch.rand(n, generator=g, dtype=torch.float64)  # distances to the fitted samples [spreads]
    s_fb = torch.tensor([3e-5, 5e-5, 2e-5], dtype=torch.float64)
    z = torch.randn(n, 3, generator=g, dtype=torch.float64)
    sigma, c = fit_fallback_growth(s_fb * (1.0 + 0.5 * d[:, None] ** 2).sqrt() * z, d)
    torch.testing.assert_close(torch.tensor(sigma, dtype=torch.float64), s_fb, rtol=0.1, atol=0.0)
    assert c == pytest.approx(0.5, rel=0.2)
    sigma, c = fit_fallback_growth(s_fb * z, d)  # residuals that do not grow: (almost) no growth
    torch.testing.assert_close(torch.tensor(sigma, dtype=torch.float64), s_fb, rtol=0.1, atol=0.0)
    assert c < 0.01
    with pytest.raises(ValueError, match="e must be"):
        fit_fallback_growth(z, d[:10])


def test_the_fallbacks_scale_with_a_given_growth_is_recovered_from_its_own_residuals():
    g = torch.Generator().manual_seed(4)
    n = 6000
    d = 3.0 * torch.rand(n, generator=g, dtype=torch.float64)
    s_fb = torch.tensor([3e-5, 5e-5, 2e-5], dtype=torch.float64)
    z = torch.randn(n, 3, generator=g, dtype=torch.float64)
    e = s_fb * (1.0 + 0.5 * d[:, None] ** 2).sqrt() * z
    torch.testing.assert_close(
        torch.tensor(fit_fallback_scale(e, d, 0.5), dtype=torch.float64), s_fb, rtol=0.05, atol=0
    )
    # a growth that is too steep for these residuals gives a smaller scale (the shape is taken as given)
    assert all(a < 0.8 * b for a, b in zip(fit_fallback_scale(e, d, 4.0), s_fb.tolist()))
    with pytest.raises(ValueError, match="growth"):
        fit_fallback_scale(e, d, -1.0)
    with pytest.raises(ValueError, match="e must be"):
        fit_fallback_scale(e, d[:10], 0.5)


def test_the_fallbacks_part_fades_in_with_the_predictions_gate_and_grows_with_distance():
    robot, gate, region = _gate(length=1.0)
    fb = [1e-4, 2e-4, 3e-4]
    gate.sigma_fallback, gate.fallback_growth = fb, 0.25
    q = region[:5] + 20.0  # many spreads away: the gate is 0, the prediction is the fallback's
    d = gate.distance(q)[:, None]
    expected = torch.tensor(fb, dtype=torch.float64) * (1.0 + 0.25 * d**2).sqrt()
    torch.testing.assert_close(gate.predictive_std(robot, q), expected, rtol=1e-6, atol=0.0)
    # part way out the fallback's part is weighted by (1 - g)^2 (the prediction mixes the two linearly)
    q = region[:50] + 0.5
    a, b, g2 = gate.variance_parts(robot, q)
    dd = gate.distance(q)[:, None]
    g = torch.exp(-0.5 * dd**2)
    h2 = torch.exp(-(dd**2))
    fb_t = torch.tensor(fb, dtype=torch.float64)
    torch.testing.assert_close(b, g**2 * (1 - h2) * FAR**2 + (1 - g) ** 2 * fb_t**2 * (1 + 0.25 * dd**2))
    torch.testing.assert_close(g2, (g**2).expand(-1, 3))
    # an infinite gate never fades the prediction: no fallback part, the model's error grows towards s_far
    robot, gate, region = _gate(length=math.inf)
    gate.sigma_fallback, gate.fallback_growth = fb, 0.25
    far = gate.predictive_std(robot, region[:5] + 20.0)
    a, _, _ = gate.variance_parts(robot, region[:5] + 20.0)
    torch.testing.assert_close(far, (a + FAR**2).sqrt())
    with pytest.raises(ValueError, match="fallback_growth"):
        gate.set_predictive(
            gate.weight_cov, gate.weight_index, gate.sigma_noise, gate.sigma_far, 8.0, 1.0, None, fb, -1
        )


def test_a_saved_gate_is_rebuilt_with_its_sigma_and_an_old_one_without(tmp_path):
    robot, gate, region = _gate(length=math.inf, scale=2.5)  # an infinite gate: config writes None (JSON)
    gate.sigma_floor = [1e-5, 2e-5, 3e-5]
    gate.sigma_fallback, gate.fallback_growth = [1e-4, 2e-4, 3e-4], 0.25
    cfg = json.loads(json.dumps({"class": "RegionGate", **gate.config()}, allow_nan=False))
    assert cfg["length"] is None and cfg["predictive"]["scale"] == 2.5
    assert cfg["predictive"]["floor"] == [1e-5, 2e-5, 3e-5]
    assert cfg["predictive"]["fallback_sigma"] == [1e-4, 2e-4, 3e-4] and cfg["predictive"]["fallback_growth"] == 0.25
    again = effect_from_config(cfg, robot)
    again.load_state_dict(gate.state_dict())
    assert again.length == math.inf and again.has_predictive
    assert (again.sigma_fallback, again.fallback_growth) == (gate.sigma_fallback, gate.fallback_growth)
    torch.testing.assert_close(again.predictive_std(robot, region[:20]), gate.predictive_std(robot, region[:20]))
    plain = RegionGate(LearnedEffect(random_features(hidden=16)), region, 0.5)
    cfg = {"class": "RegionGate", **plain.config()}
    assert cfg["predictive"] is None and not any("sigma" in k for k in plain.state_dict())
    assert not effect_from_config(cfg, robot).has_predictive
    assert predictive_sigma(MeasurementModel(robot, [plain]), region) is None
    assert predictive_sigma(MeasurementModel(robot), region) is None


def _run_dir(path, model):
    """A run directory for ``model`` as write_run_files writes one (model.json, model.pt, the robot)."""
    import shutil

    from torchcal.robot import resolve_robot_spec

    src = resolve_robot_spec("ur5")
    (path / "robot").mkdir(parents=True)
    shutil.copy2(src, path / "robot" / src.name)
    torch.save(model.state_dict(), path / "model.pt")
    meta = {
        "format": "torchcal-run-1",
        "robot_file": f"robot/{src.name}",
        "trajectory": True,
        "effects": [{"class": type(e).__name__, **e.config()} for e in model.effects],
        "method": "integrated",
    }
    (path / "model.json").write_text(json.dumps(meta, allow_nan=False))
    return path


@pytest.mark.parametrize("with_sigma", [True, False])
def test_predict_writes_sx_sy_sz_after_the_other_columns_only_where_sigma_is_defined(tmp_path, with_sigma):
    robot, gate, region = _gate(length=0.5, scale=2.0)
    model = MeasurementModel(robot, [gate] if with_sigma else [])
    run = _run_dir(tmp_path / "run", model)
    q = region[:30]
    write_measurements(tmp_path / "q.csv", Measurements(q=q, t=torch.arange(30.0, dtype=torch.float64)))
    assert main(["predict", str(run), str(tmp_path / "q.csv"), "--out", str(tmp_path / "p.csv"), "--quiet"]) == 0
    header = next(ln for ln in (tmp_path / "p.csv").read_text().splitlines() if not ln.startswith("#"))
    base = "q1,q2,q3,q4,q5,q6,x,y,z,t"
    # no covariance.pt and no measured trust level in this run directory: the gate's sigma is the only one
    # (extrapolation and the model that predicted each row are always written)
    assert header == (base + ",sx,sy,sz" if with_sigma else base) + ",extrapolation,model"
    pred = read_measurements(tmp_path / "p.csv", require_positions=True)
    if with_sigma:
        torch.testing.assert_close(pred.sigma, gate.predictive_std(model.robot, q))
    else:
        assert pred.sigma is None


def test_geometry_alone_is_kept_when_no_candidate_beats_it_in_every_piece(monkeypatch):
    """The selection rule on a stub candidate: better than geometry on average over the validation block, but only
    by its last piece (a little worse in the others) is not kept, and the run says why."""
    c = simulate(SimConfig(robot="ur5", trajectory=True, samples=400, train_samples=399, seed=2))
    run = calibrate("ur5", c.train, Options(method="kinematic", seed=0))

    def stub(trial, fit, val, setting):
        # the candidate's error: a tenth of geometry's in the last quarter of the validation block, 1.05 x before
        e = (trial.model(Context.from_measurements(val, trajectory=True)) - val.p).detach()
        w = torch.full((val.n, 1), 1.05, dtype=e.dtype)
        w[-(val.n // 4) :] = 0.1
        trial.model.add(_Offset(val.q, (w - 1.0) * e))

    monkeypatch.setattr(I, "_run_setting", stub)
    work = StageWork(run, "integrated")
    assert I.integrate_selected(work, run.train, run.hold, settings=(I.Setting("adaptive"),)) is None
    assert not work.effects
    (rej,) = work.rejections
    assert "any one of its pieces left out" in rej.reason and "geometry alone kept" in work.notes[-1]
    row = rej.evidence["selection"]["candidates"][1]
    assert row["validation_rmse_mm"] < rej.evidence["selection"]["candidates"][0]["validation_rmse_mm"]
    assert max(row["leave_one_piece_out_ratios"]) >= 1.0


def test_leave_one_piece_out_ratios():
    ref = torch.ones(8, dtype=torch.float64)
    per_piece, left_out = I.leave_one_piece_out(torch.tensor([1.0, 1, 2, 2, 1, 1, 0, 0]).double(), ref, 4)
    assert per_piece == pytest.approx([1.0, 2.0, 1.0, 0.0])
    assert left_out == pytest.approx([math.sqrt(5 / 3), math.sqrt(2 / 3), math.sqrt(5 / 3), math.sqrt(2.0)])


class _Offset(Effect):
    """A position correction given at fixed joints (the stub candidate's), zero elsewhere."""

    kind = "learned"
    acts_on = "cartesian"

    def __init__(self, q, dp):
        super().__init__(joint=None)
        self.q, self.dp = q, dp

    def forward(self, robot, ctx, p_base=None):
        if len(ctx.q) != len(self.q) or not bool((ctx.q == self.q).all()):
            return torch.zeros(len(ctx.q), 3, dtype=ctx.q.dtype)
        return self.dp @ robot.T_tracker_base()[:3, :3].detach()  # the tracker-frame offset in the base frame


def test_a_predictive_sigma_far_beyond_the_residuals_is_reported():
    e = torch.full((4, 3), 1e-4, dtype=torch.float64)
    sane = sigma_check([(e, torch.full((4, 3), 5e-5, dtype=torch.float64))])
    assert not sane["suspect"] and sane["ratio"] == pytest.approx(0.5)
    assert sane["max_sigma_mm"] == pytest.approx(0.05) and sane["max_residual_mm"] == pytest.approx(0.1)
    wide = torch.full((4, 3), 5e-5, dtype=torch.float64)
    wide[2, 1] = 7e7  # a widening factor set by a sample whose near part was nearly zero
    check = sigma_check([(e, torch.full((4, 3), 5e-5, dtype=torch.float64)), (e, wide)])
    assert check["suspect"] and check["ratio"] == pytest.approx(7e11)
    # a widening factor at its cap (region.FACTOR_SIGMA_RATIO times the largest residual) is always reported
    from torchcal.effects.region import FACTOR_SIGMA_RATIO

    capped = sigma_check([(e, torch.full((4, 3), FACTOR_SIGMA_RATIO * 1e-4, dtype=torch.float64))])
    assert capped["suspect"] and capped["ratio"] == pytest.approx(FACTOR_SIGMA_RATIO)
    inf = sigma_check([(e, torch.full((4, 3), math.inf, dtype=torch.float64))])
    assert inf["suspect"] and inf["ratio"] is None and inf["max_sigma_mm"] is None
    json.dumps(inf)  # report.json takes it as it is


def test_the_calibration_sets_both_gates_from_the_growth_the_fallback_and_both_blocks():
    """:func:`calibrate_predictive_sigma` on hand-built gates: the fallback's growth from the refits' residuals,
    its scale from the fallback's own residuals on the held-out block, then scale and floor by likelihood on
    validation widened over both blocks; both gates get the same calibration, and the evidence says so."""
    robot, val_gate, region = _gate(length=1.0, seed=0)
    _, final, _ = _gate(length=1.0, seed=0)
    g = torch.Generator().manual_seed(7)
    q_val, q_hold = region[:80] + 0.2, region[80:200] + 0.4

    def draw(n, s):
        return s * torch.randn(n, 3, generator=g, dtype=torch.float64)

    d_growth = 3.0 * torch.rand(300, generator=g, dtype=torch.float64)
    e_growth = 5e-5 * (1.0 + 0.5 * d_growth[:, None] ** 2).sqrt() * torch.randn(300, 3, generator=g).double()
    e_fb = draw(120, 4e-5)
    validation = GatedBlock(val_gate, robot, q_val, draw(80, 3e-5))
    holdout = GatedBlock(final, robot, q_hold, draw(120, 5e-5))
    ev = calibrate_predictive_sigma(validation, final, holdout, e_growth, d_growth, e_fb)
    s_fb, c = fit_fallback_growth(e_growth, d_growth)
    assert ev["fallback_growth"] == c and c > 0
    expected_fb = fit_fallback_scale(e_fb, final.distance(q_hold), c)
    assert ev["fallback_sigma_mm"] == pytest.approx([x * 1e3 for x in expected_fb], rel=1e-12)
    for gate in (val_gate, final):
        assert (gate.sigma_fallback, gate.fallback_growth) == (expected_fb, c)
    with torch.no_grad():
        parts_val, parts_hold = val_gate.variance_parts(robot, q_val), final.variance_parts(robot, q_hold)
    scale, floor = fit_predictive_scale(validation.e, *parts_val, 0.95, holdout=(holdout.e, *parts_hold))
    assert (ev["scale"], ev["floor_mm"]) == (scale, [f * 1e3 for f in floor])
    assert (val_gate.sigma_scale, val_gate.sigma_floor) == (final.sigma_scale, final.sigma_floor) == (scale, floor)
    with torch.no_grad():
        sd_val, sd_hold = val_gate.predictive_std(robot, q_val), final.predictive_std(robot, q_hold)
    assert ev["coverage_2sigma_validation"] == coverage(validation.e, sd_val)
    assert ev["coverage_2sigma_holdout"] == coverage(holdout.e, sd_hold)
    assert ev["sigma_check"] == sigma_check([(validation.e, sd_val), (holdout.e, sd_hold)])
    assert (ev["n_validation"], ev["n_holdout"], ev["sigma_length"]) == (80, 120, 1.0)
    json.dumps(ev)
    # without held-out samples: the refits alone size the fallback, validation alone the scale
    alone = calibrate_predictive_sigma(validation, final, None, e_growth, d_growth)
    assert alone["fallback_sigma_mm"] == pytest.approx([x * 1e3 for x in s_fb], rel=1e-12)
    assert alone["n_holdout"] == 0 and alone["coverage_2sigma_holdout"] is None
    with pytest.raises(ValueError, match="final gate"):
        calibrate_predictive_sigma(
            validation, final, GatedBlock(val_gate, robot, q_hold, holdout.e), e_growth, d_growth
        )


class _Shift(Effect):
    """A constant position correction (the base frame) wherever it is asked: wrong on every sample."""

    kind = "learned"
    acts_on = "cartesian"

    def __init__(self, dp):
        super().__init__(joint=None)
        self.dp = dp

    def forward(self, robot, ctx, p_base=None):
        return self.dp.expand(len(ctx.q), 3)


def test_the_held_out_samples_only_ever_shorten_the_gate():
    """The final model's gate is the shorter of validation's choice and the held-out samples' choice: a correction
    that is wrong on the held-out samples shortens a long gate to the shortest tried; one that is right there (zero
    error ungated) keeps validation's length, never a longer one; too few held-out samples keep it too."""
    c = simulate(SimConfig(robot="ur5", trajectory=True, samples=400, train_samples=399, seed=2))
    run = calibrate("ur5", c.train, Options(method="kinematic", seed=0))
    kinematic, setting = copy.deepcopy(run.model.robot), I.Setting("adaptive")
    gate = {"kinematic": kinematic, "setting": setting, "length": 4.0}
    wrong = MeasurementModel(run.model.robot, [_Shift(torch.tensor([[2e-4, 0.0, 0.0]], dtype=torch.float64))])
    ev = {}
    assert I._gate_on_holdout(wrong, run.train, run.hold, **gate, evidence=ev) == min(setting.gate_lengths)
    assert ev["gate_on_holdout"]["validation_gate_length"] == 4.0 and len(ev["gate_on_holdout"]["gates"]) == 9
    e = (run.model(Context.from_measurements(run.hold, trajectory=True)) - run.hold.p).detach()
    right = MeasurementModel(run.model.robot, [_Offset(run.hold.q, -e)])
    ev = {}
    assert I._gate_on_holdout(right, run.train, run.hold, **gate, evidence=ev) == 4.0
    assert math.isinf(ev["gate_on_holdout"]["holdout_gate_length"])
    ev = {}
    few = run.hold.subset(slice(0, I.VALIDATION_PIECES - 1))
    assert I._gate_on_holdout(wrong, run.train, few, **gate, evidence=ev) == 4.0 and not ev


@pytest.mark.parametrize("spoiled", [False, True])
def test_geometry_alone_at_nominal_steps_back_to_the_nominal_model_where_that_is_better_on_the_held_out_samples(
    spoiled,
):
    """Where the integrated method keeps geometry alone and the kinematic calibration moved no geometric element, it
    must beat the nominal stage on the held-out samples, else the run ends with the nominal model (a method never
    worse than the simpler one); a calibration that moved its geometry is not judged so."""
    c = simulate(SimConfig(robot="ur5", trajectory=True, samples=400, train_samples=399, seed=2))
    run = calibrate("ur5", c.train, Options(method="kinematic", seed=0))
    work = StageWork(run, "integrated")
    if spoiled:  # every geometric element at nominal, and an instrument pose 0.5 mm off the nominal stage's
        robot = work.model.robot
        with torch.no_grad():
            robot.groups()["geometry"].delta.zero_()
            robot.load_state_dict(run.stage("nominal").model.robot.state_dict())
            robot.groups()["instrument"].delta[0] += 5e-4
    evidence = {}
    I._keep_geometry(work, evidence, "no candidate")
    guard, nominal = evidence["nominal_guard"], run.stage("nominal")
    assert guard["passed"] is not spoiled
    if not spoiled:
        assert "moved its geometry" in guard["rule"] and work.stages[-1].name == "geometric"
        return
    assert guard["nominal_rmse_mm"] == pytest.approx(nominal.rmse * 1e3)
    assert guard["nominal_rmse_mm"] < guard["kinematic_rmse_mm"]
    assert work.stages[-1].name == "nominal" and work.stages[-1].rmse == pytest.approx(nominal.rmse)
    assert work.fits[-1].stage == "nominal" and "the nominal geometry kept" in work.notes[-1]
    torch.testing.assert_close(
        work.model(Context.from_measurements(run.hold, trajectory=True)),
        nominal.model(Context.from_measurements(run.hold, trajectory=True)),
    )
