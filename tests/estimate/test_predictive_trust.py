"""The predictive sigma (torchcal.estimate.trust): measured on held-out rows, it covers a fresh draw of the same
error, grows beyond the region, and round-trips through model.json."""

import pytest
import torch

from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.trust import Trust, fit_trust
from torchcal.robot import load_robot

F64 = torch.float64


def _rows(model, n, seed, level):
    """Poses in a box, measured as the model predicts plus an error of ``level`` [m] per axis it does not explain."""
    g = torch.Generator().manual_seed(seed)
    q = (torch.rand(n, 6, generator=g, dtype=F64) - 0.5) * 1.5
    with torch.no_grad():
        p = model(Context(q=q)) + torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor(level, dtype=F64)
    return Context(q=q), p


def test_the_level_measured_on_held_out_rows_covers_fresh_rows():
    model = MeasurementModel(load_robot("ur5"))
    level = [40e-6, 20e-6, 60e-6]
    ctx, p = _rows(model, 300, 0, level)
    model.set_region(ctx.q)
    tr = fit_trust(model, None, ctx, p, (15e-6,) * 3)
    # the moment estimate: the error's level less the noise, per axis, to the spread of 300 rows
    for a in range(3):
        assert tr.inside[a] == pytest.approx((level[a] ** 2 - 15e-6**2) ** 0.5, rel=0.15)
    fresh, p2 = _rows(model, 2000, 1, level)
    inside = model.extrapolation(fresh.q) == 0
    s = tr.std(model, fresh, None)
    with torch.no_grad():
        z = ((model(fresh) - p2).abs() / s)[inside]
    assert float((z.amax(dim=1) <= 3).double().mean()) >= 0.97
    assert 0.55 <= float(z.median()) <= 0.8
    assert fit_trust(model, None, Context(q=ctx.q[:5]), p[:5], (15e-6,) * 3) is None  # too few rows: not measured


def test_beyond_the_region_the_level_grows_towards_the_far_one_and_the_entry_round_trips():
    model = MeasurementModel(load_robot("ur5"))
    q = torch.zeros(2, 6, dtype=F64)
    q[1, 0] = 0.5
    model.set_region(q)
    tr = Trust((1e-5,) * 3, (1e-4,) * 3, (1e-3,) * 3, 1.0, 50, 0.99, 0.6)
    out = torch.zeros(4, 6, dtype=F64)
    out[:, 0] = torch.tensor([0.2, 0.6, 0.8, 1.5], dtype=F64)  # inside, then 0.1, 0.3 and 1.0 rad beyond
    s = tr.std(model, Context(q=out), None)[:, 0]
    assert float(s[0]) == pytest.approx((1e-10 + 1e-8) ** 0.5)
    assert bool((s.diff() > 0).all()) and float(s[-1]) == pytest.approx((1e-10 + 1e-6) ** 0.5, rel=1e-3)
    back = Trust.from_dict(tr.to_dict())
    assert back == tr
    for bad in ({**tr.to_dict(), "scale": 0.5}, {**tr.to_dict(), "noise_m": [1e-5, -1, 0]}, [1, 2]):
        with pytest.raises(ValueError):
            Trust.from_dict(bad)
    with pytest.raises(ValueError, match="variogram"):
        Trust.from_dict({**tr.to_dict(), "variogram": {"lag": [[0.2, 0.1]], "rho": [[0.0, 0.5]]}})
