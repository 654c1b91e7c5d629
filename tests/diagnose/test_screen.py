"""The closed loop's screen: one Gauss-Newton step from a fitted model with a candidate added at zero
(:func:`torchcal.estimate.fit.gauss_newton_step`), against the refit it stands in for."""

import copy
import math

import torch
from _cli import _golden

from torchcal.effects.joint import Compliance
from torchcal.estimate.fit import GEOMETRIC_GROUPS, errors, gauss_newton_step, solve
from torchcal.pipeline.loop import SCREEN_AGREEMENT


def _kinematic():
    """The golden campaign's kinematic run (shared: copied here), its training poses and options."""
    run = _golden().golden_run("kinematic")
    return copy.deepcopy(run.model), run.train, run.options.fit, run.identifiability


def test_the_step_lands_where_the_refit_does():
    model, train, opts, ida = _kinematic()
    model.add(Compliance(2))  # the campaign's joint-2 compliance, absent from the kinematic model
    refit = copy.deepcopy(model)
    step = gauss_newton_step(model, train, GEOMETRIC_GROUPS, opts, trajectory=False, identifiability=ida)
    fit = solve(refit, train, GEOMETRIC_GROUPS, opts, "refit", trajectory=False, effects=True, identifiability=ida)
    assert not step.singular
    assert SCREEN_AGREEMENT <= step.agreement <= 1 / SCREEN_AGREEMENT, step
    assert step.cost_after < 0.8 * step.cost_before  # the compliance explains a quarter of what the geometry left
    k_step, k_fit = float(model.effects[-1].k.detach()), float(refit.effects[-1].k.detach())
    assert k_fit > 0 and abs(k_step - k_fit) < 0.02 * k_fit, (k_step, k_fit)
    e_step, e_fit = errors(model, train, False), errors(refit, train, False)
    assert abs(float(e_step.square().mean().sqrt() / e_fit.square().mean().sqrt()) - 1) < 1e-3
    # the BIC the loop's refits record (its n ln(RSS / n) + k ln n over every residual row): the step's within 1
    n = fit.result.n_obs
    bic_fit = n * math.log(float(fit.result.residuals.square().sum()) / n) + len(fit.result.x) * math.log(n)
    assert step.rows == n and abs(step.bic - bic_fit) < 1.0, (step.bic, bic_fit)


def test_a_column_the_model_already_has_is_singular_and_moves_nothing():
    model, train, opts, ida = _kinematic()
    model.add(Compliance(2))
    model.add(Compliance(2))  # the same column twice: an exact null space
    before = copy.deepcopy(model.state_dict())
    step = gauss_newton_step(model, train, GEOMETRIC_GROUPS, opts, trajectory=False, identifiability=ida)
    assert step.singular and abs(step.smallest) < 1e-14, step
    assert "compliance" in step.hint
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())
