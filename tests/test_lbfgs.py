"""torchcal._lbfgs is torch.optim.LBFGS with the strong-Wolfe line search, to the bit: the same closure, stepped once
by each, evaluates the same points in the same order and ends at the same parameters."""

import pytest
import torch

from torchcal import _lbfgs
from torchcal.effects.gp import _exact_loss_and_grad, _initial, pair_distances
from torchcal.errors import EstimationError

F64 = torch.float64
#: the settings of the GP's evidence fit (effects/gp.py, fit_hyperparameters)
GP = {"max_iter": 40, "history_size": 20, "tolerance_grad": 1e-6, "tolerance_change": 1e-9}


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t.contiguous().view(torch.int64)


def _one(loss_and_grad, theta0: torch.Tensor, use_torch: bool, **kw):
    """``(points, losses, final theta)`` of torch.optim.LBFGS (``use_torch``) or torchcal._lbfgs.minimize.

    ``loss_and_grad(theta) -> (loss, grad)``; with ``grad`` None the closure calls ``loss.backward()`` (as the GP's
    sparse fit does), else it sets ``theta.grad`` itself (as its exact fit does)."""
    theta = theta0.clone().requires_grad_(True)
    points, losses = [], []

    def closure():
        theta.grad = None
        points.append(theta.detach().clone())
        loss, grad = loss_and_grad(theta)
        if grad is None:
            loss.backward()
        else:
            theta.grad = grad
        losses.append(float(loss.detach()))
        return loss

    if use_torch:
        torch.optim.LBFGS([theta], lr=1.0, line_search_fn="strong_wolfe", **kw).step(closure)
    else:
        _lbfgs.minimize(closure, theta, lr=1.0, **kw)
    return torch.stack(points), losses, theta.detach().clone()


def _both(loss_and_grad, theta0: torch.Tensor, **kw):
    """:func:`_one` by torch, then by torchcal._lbfgs."""
    return [_one(loss_and_grad, theta0, use_torch, **kw) for use_torch in (True, False)]


def _assert_same(runs):
    (p0, l0, t0), (p1, l1, t1) = runs
    assert p0.shape == p1.shape, f"{len(p0)} evaluations by torch, {len(p1)} by torchcal._lbfgs"
    assert torch.equal(_bits(p0), _bits(p1))
    assert l0 == l1
    assert torch.equal(_bits(t0), _bits(t1))


def _rosenbrock(theta):
    x = theta
    return (100.0 * (x[1:] - x[:-1].square()).square() + (1.0 - x[:-1]).square()).sum(), None


@pytest.mark.parametrize(
    "start, kw",
    [
        ([-1.2, 1.0], GP),
        ([-1.2, 1.0, -0.5, 0.8, 1.3, -2.0], {"max_iter": 60}),  # torch's defaults otherwise
        ([-1.2, 1.0, 0.3], {"max_iter": 200, "max_eval": 90, "history_size": 3}),  # the history and evaluations cap
    ],
)
def test_rosenbrock_is_minimised_as_torch_does(start, kw):
    runs = _both(_rosenbrock, torch.tensor(start, dtype=F64), **kw)
    _assert_same(runs)
    points, losses, theta = runs[1]
    assert len(points) > 20  # a real run: many iterations and line-search steps
    assert losses[-1] < 1e-3 * losses[0]


def test_a_wall_of_huge_losses_with_zero_gradient_is_handled_as_torch_does():
    # the GP's closure answers a trial point it cannot evaluate with a loss of 1e10 and a zero gradient, which sends
    # the line search back: here beyond x_0 = 0.8, which the quadratic's first full steps overshoot
    w = torch.tensor([1.0, 4.0, 0.5], dtype=F64)
    target = torch.tensor([3.0, -1.0, 2.0], dtype=F64)

    def wall(theta):
        if float(theta[0].detach()) > 0.8:
            return torch.tensor(1e10, dtype=F64), torch.zeros_like(theta)
        th = theta.detach()
        return (w * (th - target).square()).sum(), 2.0 * w * (th - target)

    runs = _both(wall, torch.zeros(3, dtype=F64), **GP)
    _assert_same(runs)
    losses = runs[1][1]
    assert any(v == 1e10 for v in losses)  # the wall was hit
    assert min(losses) < 0.5 * losses[0]


def test_the_gp_evidence_fit_is_minimised_as_torch_does():
    g = torch.Generator().manual_seed(3)
    n, d = 60, 2
    x = torch.rand(n, d, generator=g, dtype=F64) * 4.0 - 2.0
    y = torch.stack([torch.sin(2.0 * x[:, 0]) * x[:, 1], torch.cos(x[:, 0] + x[:, 1])], dim=1)
    y = y + 0.05 * torch.randn(n, 2, generator=g, dtype=F64)
    y = (y - y.mean(0)) / y.std(0)
    periodic = torch.zeros(d, dtype=torch.bool)
    pairs = pair_distances(x, periodic)
    centre = _initial(d, d, False)

    def evidence(theta):
        # as effects/gp.py's closure: a trial point whose kernel is not positive definite, or not finite, gets 1e10
        try:
            loss, grad = _exact_loss_and_grad(theta, pairs, y, False, centre)
        except EstimationError:
            loss, grad = torch.tensor(1e10, dtype=F64), torch.zeros_like(theta)
        if not bool(torch.isfinite(loss)) or not bool(torch.isfinite(grad).all()):
            loss, grad = torch.tensor(1e10, dtype=F64), torch.zeros_like(theta)
        return loss, grad

    runs = _both(evidence, centre, **GP)
    _assert_same(runs)
    points, losses, theta = runs[1]
    assert len(points) > 10
    assert min(losses) < losses[0] - 0.1  # the evidence per row improved


def test_a_start_at_a_stationary_point_evaluates_once():
    runs = _both(_rosenbrock, torch.ones(4, dtype=F64), **GP)
    _assert_same(runs)
    assert len(runs[1][0]) == 1
