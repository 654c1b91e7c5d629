"""The trust's variogram (torchcal.estimate.trust.correction_variogram) takes a learned GP's mean at the moved rows
from its kernel at the unmoved ones (GPCorrection.moved_means): the same numbers as evaluating the model there."""

import dataclasses

import pytest
import torch

from torchcal.effects import Context, GPCorrection, MeasurementModel
from torchcal.estimate import trust
from torchcal.robot import load_robot

F64 = torch.float64


def _gp(additive: str, ard: bool, extras: tuple[str, ...] = (), m: int = 40) -> GPCorrection:
    """A GP whose buffers are set by hand (no fit): seeded inducing inputs, weights and hyperparameters."""
    g = torch.Generator().manual_seed(5)
    eff = GPCorrection(6, m, extras=extras, additive=additive, ard=ard, exact=True)
    d = 6 + len(extras)
    with torch.no_grad():
        eff.inducing.copy_((torch.rand(m, d, generator=g, dtype=F64) * 2 - 1) * 1.5)
        eff.weights.copy_(torch.randn(m, 3, generator=g, dtype=F64))
        eff.add_var.copy_(0.05 + torch.rand(d, generator=g, dtype=F64) * 0.3)
        eff.add_len.copy_(0.3 + torch.rand(d, generator=g, dtype=F64))
        eff.ard_var.fill_(0.4 if ard else 0.0)
        eff.ard_len.copy_(0.5 + torch.rand(d, generator=g, dtype=F64))
        eff.y_scale.copy_(torch.tensor([1e-4, 2e-4, 5e-5], dtype=F64))
        eff.y_mean.copy_(torch.tensor([1e-5, -2e-5, 0.0], dtype=F64))
        eff.x_offset[6:] = 100.0
        eff.x_scale[6:] = 50.0
    return eff


def _ctx(n: int, extras: tuple[str, ...] = ()) -> Context:
    g = torch.Generator().manual_seed(3)
    q = (torch.rand(n, 6, generator=g, dtype=F64) - 0.5) * 2.0
    t = 100.0 + 30.0 * torch.randn(n, generator=g, dtype=F64) if "t" in extras else None
    return Context(q=q, t=t)


@pytest.mark.parametrize("additive,ard,extras", [("rbf", True, ()), ("periodic", True, ("t",)), ("rbf", False, ())])
def test_moved_means_equal_the_mean_at_the_moved_rows(additive, ard, extras):
    eff, ctx = _gp(additive, ard, extras), _ctx(300, extras)  # 300 rows: two of the GP's row blocks
    moves = {j: [ctx.q[:, j] + h for h in (0.01, -0.3, 1.2)] for j in (0, 3, 5)}
    got = eff.moved_means(ctx, moves)
    for j, cols in moves.items():
        for col, mean in zip(cols, got[j]):
            q = ctx.q.clone()
            q[:, j] = col
            with torch.no_grad():
                ref = eff(None, dataclasses.replace(ctx, q=q))
            assert torch.allclose(mean, ref, rtol=1e-12, atol=1e-12 * float(ref.abs().max()))


def _reference_variogram(model, ctx):
    """The variogram as its definition says: each lag's moved rows evaluated anew, one move at a time."""
    far = trust.without_fading(model)
    lo, hi = model.region[0], model.region[1]
    with torch.no_grad():
        c0 = model(ctx) - far(ctx)
        var = float((c0 - c0.mean(0)).square().sum(1).mean())
        rhos = []
        for j in range(ctx.q.shape[1]):
            rho = [0.0]
            for f in trust.LAGS[1:]:
                h = f * float(hi[j] - lo[j])
                q = ctx.q.clone()
                up = q[:, j] + h <= hi[j]
                q[:, j] = torch.where(up, q[:, j] + h, q[:, j] - h)
                rows = torch.nonzero(up | (q[:, j] >= lo[j])).flatten()
                moved = dataclasses.replace(ctx.subset(rows), q=q[rows])
                g = 0.5 * float((model(moved) - far(moved) - c0[rows]).square().sum(1).mean())
                rho.append(max(rho[-1], min(1.0, g / var)))
            rhos.append(rho)
    return rhos


@pytest.mark.parametrize("batch_rows", [trust.BATCH_ROWS, 150])  # all moves in one batch; batches of one or two
def test_the_variogram_is_that_of_the_model_evaluated_at_the_moved_rows(monkeypatch, batch_rows):
    monkeypatch.setattr(trust, "BATCH_ROWS", batch_rows)
    model = MeasurementModel(load_robot("ur5"))
    ctx = _ctx(120)
    model.add(_gp("rbf", True))
    model.set_region(ctx.q[:100])  # rows beyond the region too: a move may leave it (those rows are left out)
    inside = model.extrapolation(ctx.q) == 0
    ctx = ctx.subset(torch.nonzero(inside).flatten())
    lags, rho = trust.correction_variogram(model, ctx)
    assert len(lags) == len(rho) == 6 and all(len(r) == len(trust.LAGS) for r in rho)
    assert max(r[-1] for r in rho) > 0.05  # the GP varies along the joints: rho measured, not all zero
    for r, s in zip(rho, _reference_variogram(model, ctx)):
        assert r == pytest.approx(s, rel=1e-10, abs=1e-14)
