"""experiments/multisine_field.py's ridge reference: a field drawn on its own random features is recovered, and a
penalty shrinks it; scripts/multisine_field.py on one tiny trajectory prints its table."""

import pytest
import torch
from _cli import run_script

from experiments.multisine_field import _features, _ridge


def test_the_ridge_reference_recovers_a_field_on_its_own_features():
    g = torch.Generator().manual_seed(0)
    q = (torch.rand(400, 6, generator=g, dtype=torch.float64) - 0.5) * 2.0
    X = _features(q, 32, 2.0, seed=3)
    w = torch.randn(X.shape[1], 3, generator=g, dtype=torch.float64) * 0.1
    y = X @ w
    torch.testing.assert_close(_ridge(X, y, 1e-12), w, atol=1e-6, rtol=0)
    shrunk = _ridge(X, y, 10.0)
    assert (X @ shrunk - y).norm() > 0.1 * y.norm()  # a heavy penalty leaves most of the field
    assert X.shape == (400, 33) and bool((X[:, -1] == 1.0).all())


@pytest.mark.slow
def test_the_script_prints_its_table():
    res, _ = run_script("multisine_field.py", "--seeds", "0", "--samples", "400", "--train-samples", "320", "--json")
    (row,) = res["rows"]
    assert row["seed"] == 0 and row["geometry_mm"] > 0 and row["integrated_mm"] > 0
    assert row["ridge"]["continuation_rmse_mm"] > 0 and res["target"] == {"median_at_most": 0.8, "worst_at_most": 1.02}
    assert res["median_integrated_over_geometry"] == pytest.approx(row["integrated_over_geometry"])
