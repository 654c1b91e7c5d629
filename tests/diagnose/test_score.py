"""Candidates and score tests: which effects are considered, the chi-square tail, and that the score
statistic predicts what the joint refit then gains."""

import dataclasses
import math

import pytest
import torch

from torchcal.diagnose import Candidate, candidates, score_candidates
from torchcal.effects import Context
from torchcal.estimate.fit import solve
from torchcal.pipeline import Options, calibrate
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.stats import chi2_sf_log10


def test_chi2_tail_known_values_and_far_tail():
    # textbook quantiles: chi2_{0.95}(1) = 3.8415, chi2_{0.99}(4) = 13.277, chi2_{0.95}(6) = 12.592
    for x, k, p in ((3.841458820694124, 1, 0.05), (13.276704135987622, 4, 0.01), (12.591587243743977, 6, 0.05)):
        got, l10 = chi2_sf_log10(x, k)
        assert got == pytest.approx(p, rel=1e-9)
        assert l10 == pytest.approx(math.log10(p), rel=1e-9)
    # where p is still representable, the asymptotic tail used beyond it agrees with it
    for k in (1, 4, 6):
        p, l10 = chi2_sf_log10(1100.0, k)
        assert p > 0
        y, a = 550.0, 0.5 * k
        asym = ((a - 1) * math.log(y) - y - math.lgamma(a) + math.log1p((a - 1) / y)) / math.log(10)
        assert asym == pytest.approx(l10, abs=2e-5)
    assert chi2_sf_log10(5000.0, 1)[1] < -1000  # no underflow to -inf or 0


def test_candidates_static_poses_and_trajectory():
    c = simulate(SimConfig(robot="ur5", poses=60, test_poses=0, seed=1))
    robot = c.model.robot
    cands, skipped = candidates(robot, Context.from_measurements(c.train, trajectory=False))
    names = {x.name for x in cands}
    left_out = {s["name"]: s["reason"] for s in skipped}
    # joint 1 turns about the vertical: no gravity torque, so neither compliance nor a changing flank
    assert "compliance:1" in left_out and "backlash:1" in left_out
    assert {"compliance:2", "backlash:3", "cyclic:1", "cyclic:6", "drift:t", "drift:temperature"} <= names
    assert not names & set(left_out)
    # along a trajectory the flank follows the motion, so joint 1 has a backlash candidate
    traj = simulate(SimConfig(robot="ur5", trajectory=True, samples=300, train_samples=200, seed=1))
    cands, _ = candidates(robot, Context.from_measurements(traj.train, trajectory=True))
    assert "backlash:1" in {x.name for x in cands}
    # without temperature or time columns there is no drift candidate
    ctx = Context(q=c.train.q)
    cands, skipped = candidates(robot, ctx)
    assert not [x for x in cands if x.kind == "drift"]
    assert {"drift:t", "drift:temperature"} <= {s["name"] for s in skipped}


def test_score_statistic_predicts_the_refit_gain():
    """Score test = first-order decrease of the weighted sum of squares: compare with the actual joint refit."""
    c = simulate(
        SimConfig(robot="ur5", poses=300, test_poses=0, seed=2, effects=[EffectSpec.parse("compliance:3=20um")])
    )
    opts = Options.of(method="kinematic", stat_tol=0.0)
    run = calibrate("ur5", c.train, opts)
    train = c.train.subset(run.train_idx)
    geo = run.fits[-1]
    ctx = Context.from_measurements(train, trajectory=False)
    cand = Candidate("compliance", 3)
    score = score_candidates(run.model, geo.result, ctx, train.p, geo.whitening, cands=[cand])[0]
    ss0 = float(geo.result.residuals.square().sum())
    run.model.add(cand.make())
    refit = solve(
        run.model,
        train,
        ("geometry", "instrument", "tool"),
        opts.fit.geometric(),  # the priors of the fit the score is taken at (the kinematic calibration's)
        "x",
        trajectory=False,
        effects=True,
        identifiability=geo.identifiability,
    )
    ss1 = float(refit.result.residuals.square().sum())
    assert score.delta_ss == pytest.approx(ss0 - ss1, rel=0.02)
    assert score.statistic > 100 and score.identifiable and score.k == 1
    assert score.p_bonferroni == pytest.approx(min(1.0, score.p_value), rel=1e-12)  # one candidate


def test_a_candidate_the_geometry_already_has_is_not_identifiable():
    """Cyclic terms of a joint that never moves are a constant joint offset: the geometry has it."""
    c = simulate(SimConfig(robot="ur5", poses=200, test_poses=0, seed=3))
    m = c.train
    q = m.q.clone()
    q[:, 5] = 0.3  # joint 6 parked
    m = dataclasses.replace(m, q=q)
    run = calibrate("ur5", m, Options(method="kinematic"))
    train = m.subset(run.train_idx)
    geo = run.fits[-1]
    ctx = Context.from_measurements(train, trajectory=False)
    s = score_candidates(run.model, geo.result, ctx, train.p, geo.whitening, cands=[Candidate("cyclic", 6)])[0]
    assert not s.identifiable and s.independence < 1e-6 and not s.significant(0.01)
    # and the candidate list leaves it out in the first place
    assert "cyclic:6" not in {x.name for x in candidates(run.model.robot, ctx)[0]}


def test_all_candidates_columns_in_one_pass_equal_each_candidate_s_own(monkeypatch):
    """The columns of every candidate from one forward-mode pass with all of them added (each at zero) are those
    of the model with that candidate alone, to the bit, also when the pass is split into batches; the model
    carries a named effect of its own (a compliance), as in the closed loop's later rounds."""
    from torchcal.diagnose import score as S
    from torchcal.estimate.problem import linear_kinematics

    c = simulate(
        SimConfig(robot="ur5", poses=150, test_poses=0, seed=4, effects=[EffectSpec.parse("compliance:2=30um")])
    )
    run = calibrate("ur5", c.train, Options(method="kinematic"))
    train = c.train.subset(run.train_idx)
    geo = run.fits[-1]
    ctx = Context.from_measurements(train, trajectory=False)
    run.model.add(Candidate("compliance", 2).make())
    cands, _ = candidates(run.model.robot, ctx)
    cands = [x for x in cands if x.name != "compliance:2"]
    assert len({x.kind for x in cands}) >= 3 and sum(x.n_params for x in cands) > 10
    fk = linear_kinematics(run.model, ctx)
    alone = [S.candidate_columns(run.model, x, ctx, train.p, geo.whitening, fk) for x in cands]
    together = S.all_candidate_columns(run.model, cands, ctx, train.p, geo.whitening, fk)
    assert len(together) == len(cands) and all(torch.equal(a, b) for a, b in zip(alone, together))
    monkeypatch.setattr(S, "COLUMN_BUDGET", 5 * len(train.q))  # batches of at most 5 parameters
    batched = S.all_candidate_columns(run.model, cands, ctx, train.p, geo.whitening, fk)
    assert all(torch.equal(a, b) for a, b in zip(alone, batched))
