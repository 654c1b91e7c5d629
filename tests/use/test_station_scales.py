"""The predicted error of a re-stationing against what its points' leave-one-out errors bear out
(:func:`torchcal.use.station._loo_scale`): untouched within the chi-square band, scaled to its nearer end outside."""

import math
from types import SimpleNamespace

import torch

from torchcal.estimate.lm import chi2_quantile
from torchcal.use.station import ALPHA, _loo_scale


def _station(loo):
    return SimpleNamespace(loo=torch.as_tensor(loo, dtype=torch.float64), warnings=[])


def test_leave_one_out_errors_like_the_prediction_leave_it():
    sigma = torch.full((10, 3), 1e-5, dtype=torch.float64)
    st = _station([math.sqrt(3) * 1e-5] * 10)  # |loo| = |sigma| at every point: 3 sum(...) = 3 n
    assert _loo_scale(st, sigma) == 1.0 and not st.warnings


def test_smaller_and_larger_errors_scale_it_to_the_band():
    sigma = torch.full((10, 3), 1e-5, dtype=torch.float64)
    norm = math.sqrt(3) * 1e-5
    small = _station([0.2 * norm] * 10)
    s = _loo_scale(small, sigma)
    t = 3.0 * 10 * 0.04
    assert math.isclose(s, math.sqrt(t / chi2_quantile(ALPHA / 2, 30)), rel_tol=1e-9)
    assert s < 1.0 and "smaller" in small.warnings[0]
    large = _station([5 * norm] * 10)
    s = _loo_scale(large, sigma)
    assert math.isclose(s, math.sqrt(3.0 * 10 * 25 / chi2_quantile(1 - ALPHA / 2, 30)), rel_tol=1e-9)
    assert s > 1.0 and "larger" in large.warnings[0]


def test_too_few_leave_one_out_errors_tell_nothing():
    sigma = torch.full((6, 3), 1e-5, dtype=torch.float64)
    st = _station([1e-7, 1e-7, 1e-7, 1e-7, float("nan"), float("nan")])  # 4 defined
    assert _loo_scale(st, sigma) == 1.0
