"""A fitted joint-angle function must be determined by the poses it was fitted on (never worse than without it)."""

import math

import torch

from torchcal.effects import Compliance, Cyclic, Transmission, joint_function_check

F64 = torch.float64


def _poses(lo: float, hi: float, n: int = 200, dof: int = 6, joint: int = 2) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    q = torch.rand(n, dof, generator=g, dtype=F64) * 2.0 - 1.0
    q[:, joint - 1] = lo + (hi - lo) * torch.rand(n, generator=g, dtype=F64)
    return q


def test_a_harmonic_seen_over_its_period_passes():
    q = _poses(-math.pi, math.pi)
    eff = Cyclic(2, harmonics=(4,), a=[2e-4], b=[-1e-4])
    assert joint_function_check(eff, q) is None


def test_a_harmonic_seen_over_a_narrow_range_passes_when_its_terms_add_up():
    q = _poses(0.4, 0.9)
    eff = Cyclic(2, harmonics=(1, 2), a=[3e-4, 1e-4], b=[0.0, 5e-5])
    assert joint_function_check(eff, q) is None


def test_cancelling_terms_are_refused():
    # harmonics 1..6 with 40 rad amplitudes that sum to about 1e-4 rad on a 0.3 rad range: the fit of a real
    # learning-curve subset looked like this and gave 560 mm just beyond its poses
    q = _poses(0.5, 0.8)
    orders = (1, 2, 3, 4, 5, 6)
    qj = q[:, 1]
    X = torch.cat(
        [
            torch.sin(qj[:, None] * torch.tensor(orders, dtype=F64)),
            torch.cos(qj[:, None] * torch.tensor(orders, dtype=F64)),
        ],
        dim=1,
    )
    target = 1e-4 * torch.sin(7.0 * qj)
    big = torch.full((12,), 40.0, dtype=F64)
    # a coefficient vector of size 40 whose function on the poses is the small target (least-norm correction)
    coef = big + torch.linalg.lstsq(X, (target - X @ big)[:, None]).solution[:, 0]
    eff = Cyclic(2, harmonics=orders, a=coef[:6], b=coef[6:])
    why = joint_function_check(eff, q)
    assert why is not None and "cancel" in why


def test_other_kinds_and_polynomials():
    q = _poses(-1.0, 1.0)
    assert joint_function_check(Compliance(2, k=1e-6), q) is None
    assert joint_function_check(Transmission(2, degree=3, c=[1e-4, -5e-5, 2e-5]), q) is None
    # a quadratic and a linear term that cancel over a narrow range far from zero
    q = _poses(1.0, 1.05)
    assert "cancel" in joint_function_check(Transmission(2, degree=2, c=[-1.025e-2, 1e-2]), q)
