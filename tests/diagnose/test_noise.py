"""The instrument's noise level as the data tell it, and the reading of a failed global test
(:mod:`torchcal.diagnose.noise`)."""

import math

import pytest
import torch

from torchcal.diagnose.noise import MISTAKE_SHARE, global_test_reading, noise_level

F64 = torch.float64


def _revisited(groups: int, visits: int, sigma: float, seed: int = 0):
    """``groups`` poses measured ``visits`` times each: a residual of the same smooth model error at each pose (what
    the model leaves there, 0.1 mm) plus noise of ``sigma`` per axis per visit."""
    g = torch.Generator().manual_seed(seed)
    q0 = torch.rand(groups, 6, generator=g, dtype=F64) * 6 - 3
    q = q0.repeat_interleave(visits, 0) + 1e-5 * torch.randn(groups * visits, 6, generator=g, dtype=F64)
    systematic = 1e-4 * torch.sin(q0[:, :3] * 2).repeat_interleave(visits, 0)
    return q, systematic + sigma * torch.randn(groups * visits, 3, generator=g, dtype=F64)


def test_revisits_measure_the_noise_whatever_the_model_leaves():
    q, r = _revisited(200, 2, 20e-6)
    level = noise_level(q, r, sigma=None, assumed=15e-6)
    assert level.source == "revisits" and level.dof == 200
    assert level.sigma_m == pytest.approx(20e-6, rel=0.1)  # 600 squares: a 6 % standard error


def test_without_revisits_the_stated_then_the_assumed_noise():
    q, r = _revisited(50, 1, 20e-6)
    stated = noise_level(q, r, sigma=torch.full((50, 3), 1e-5, dtype=F64), assumed=15e-6)
    assert (stated.source, stated.sigma_m) == ("stated", pytest.approx(1e-5))
    assumed = noise_level(q, r, sigma=None, assumed=15e-6)
    assert (assumed.source, assumed.sigma_m, assumed.dof) == ("assumed", 15e-6, 0)
    assert "assumed" in assumed.words() and "--tracker-noise" in assumed.words()


@pytest.mark.parametrize(
    "passed, share, reading",
    [(True, 1.0, "agrees"), (False, 3.3e-4, "model"), (False, 2 * MISTAKE_SHARE, "mistake")],
)
def test_the_reading_of_a_global_test(passed, share, reading):
    q, r = _revisited(50, 1, 20e-6)
    level = noise_level(q, r, sigma=None, assumed=1e-5)
    out = global_test_reading({"passed": passed}, level, 1e-4, share * 1.3, 1.3)
    assert out["reading"] == reading
    assert out["times_noise"] == pytest.approx(1e-4 / (math.sqrt(3) * 1e-5))
    assert out["unexplained_mm"] == pytest.approx(0.1) and out["noise"]["unit"] == "m"
