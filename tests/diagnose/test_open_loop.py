"""The closed loop with open-form candidates (torchcal.diagnose.tracing) on formula campaigns of torchcal.sim.outside.

The loop alone (``Options(learned=False)``): the effect named at the right place with its form, the held-out error
next to the true-form model, nothing named on clean data, and an ``unexplained`` entry where no form fits.
"""

import copy
import dataclasses

import pytest
import torch

from torchcal.effects import Cyclic
from torchcal.estimate.fit import errors, solve
from torchcal.pipeline import Options, calibrate
from torchcal.sim.campaign import SimConfig
from torchcal.sim.outside import OutsideEffect, simulate_outside
from torchcal.stats import rmse

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _loop(train):
    return calibrate("ur5", train, Options.of(seed=1, learned=False, holdout=0.01))


def test_third_harmonic_on_a_wrist_joint_is_named_with_its_order():
    c = simulate_outside(
        [OutsideEffect("harmonic", joint=6, order=3, size=3e-5)], SimConfig(poses=800, test_poses=200, seed=5)
    )
    run = _loop(c.train)
    assert [e["name"] for e in run.effects_report] == ["cyclic:6"]
    e = run.effects_report[0]
    assert e["params"]["order"] == [3] and e["params"]["form"] == "fourier"
    assert e["evidence"]["form"]["bic_table"] and e["evidence"]["localisation"]["variable"] == "q6"
    assert run.diagnosis.unexplained == []
    # the true form (3rd harmonic on joint 6) refitted jointly with the geometry, no search
    true = copy.deepcopy(run.stages[1].model)
    true.add(Cyclic(6, harmonics=[3]))
    tr = c.train.subset(run.train_idx)
    solve(
        true,
        tr,
        ("geometry", "instrument", "tool"),
        run.options.fit,
        "true",
        trajectory=False,
        effects=True,
        identifiability=run.fits[1].identifiability,
    )
    assert rmse(errors(run.model, c.test, False)) <= 1.2 * rmse(errors(true, c.test, False))


def test_clean_campaign_names_nothing_and_leaves_nothing_unexplained():
    c = simulate_outside([], SimConfig(poses=800, test_poses=200, seed=5))
    run = _loop(c.train)
    assert run.effects_report == [] and run.diagnosis.unexplained == []


def test_structure_without_a_form_is_reported_unexplained():
    c = simulate_outside([], SimConfig(poses=800, test_poses=200, seed=7))
    q3 = c.train.q[:, 2]
    dp = torch.zeros_like(c.train.p)
    dp[:, 2] = 80e-6 * torch.exp(-(((q3 - float(q3.median())) / 0.15) ** 2))  # a sharp bump no form describes
    run = _loop(dataclasses.replace(c.train, p=c.train.p + dp))
    assert not run.fits[-1].global_test["passed"]
    unx = run.diagnosis.unexplained
    assert unx and all(0 < u["share"] < 1 and u["p_bonferroni"] < 0.01 and u["reason"] for u in unx)
    assert {"variable", "share", "evidence", "smooth"} <= set(unx[0])


def test_a_candidate_whose_refit_fails_is_rejected_with_the_reason_not_the_run():
    """Real data (UR10 Series C) made a candidate's validation refit rank deficient; the loop must reject that
    candidate and say why instead of ending the calibration with an error."""
    from types import SimpleNamespace

    from torchcal.effects import MeasurementModel
    from torchcal.errors import EstimationError
    from torchcal.pipeline.loop import _validate
    from torchcal.robot import load_robot

    def failing_fit(model, data, stage, **kw):
        raise EstimationError(f"{stage}: least squares failed_solve: singular")

    cand = SimpleNamespace(
        name="drift:temperature", make=lambda: __import__("torchcal").effects.Drift("temperature", "scale", rates=[0.0])
    )
    score = SimpleNamespace(
        candidate=cand, statistic=12.0, k=1, log10_p=-3.0, to_dict=lambda: {"test": "score test", "p_bonferroni": 1e-3}
    )
    e_base = torch.full((5,), 1e-4, dtype=torch.float64)
    fit_part = SimpleNamespace(q=torch.zeros(5, 6, dtype=torch.float64))  # only its joint range is read
    v = _validate(
        score,
        1,
        base=MeasurementModel(load_robot("ur5")),
        e_base=e_base,
        fit_on=failing_fit,
        fit_part=fit_part,
        val_part=SimpleNamespace(q=torch.zeros(2, 6, dtype=torch.float64)),  # only its size is said
        trajectory=False,
        alpha_val=0.05,
    )
    assert not v.passed and "refit on the fitting poses failed" in v.reason and "singular" in v.reason
    assert torch.equal(v.errors, e_base)


def test_a_failing_global_test_without_a_localised_variable_is_not_silent():
    """Noise twice the stated tracker sigma: the global test fails, yet no variable carries structure. The report
    still says so: the strongest variable, marked not significant, with a reason."""
    c = simulate_outside([], SimConfig(poses=400, test_poses=20, seed=9, sigma_tracker=30e-6, write_sigma=False))
    run = calibrate("ur5", c.train, Options.of(seed=1, learned=False, holdout=0.01, sigma_tracker=15e-6))
    assert not run.fits[-1].global_test["passed"] and run.effects_report == []
    unx = run.diagnosis.unexplained
    assert len(unx) == 1 and unx[0]["significant"] is False and unx[0]["p_bonferroni"] >= 0.01
    assert "no variable is significant" in unx[0]["reason"] and 0 <= unx[0]["share"] < 1
