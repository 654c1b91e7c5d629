"""scripts/trust_coverage.py: its splits, its measure, and (with the real UR10 data) the coverage of sx, sy, sz."""

import os
from pathlib import Path

import pytest
import torch
from _cli import run_script

from experiments.trust_coverage import coverage, split
from torchcal.data import Measurements

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "real" / "ur10-ipa"
F64 = torch.float64


def test_the_q2_split_trains_on_the_central_70_percent_and_the_grouped_split_keeps_revisits_together():
    g = torch.Generator().manual_seed(0)
    q = torch.rand(200, 6, generator=g, dtype=F64) * 2 - 1
    q[100:110] = q[:10]  # ten revisits
    m = Measurements(q=q)
    tr, te = split(m, "q2-central")
    lo, hi = float(q[:, 1].min()), float(q[:, 1].max())
    mid, half = (lo + hi) / 2, 0.35 * (hi - lo)
    assert bool(((q[tr, 1] - mid).abs() <= half).all()) and bool(((q[te, 1] - mid).abs() > half).all())
    assert len(tr) + len(te) == 200
    tr, te = split(m, "grouped")
    for k in range(10):
        assert (k in tr.tolist()) == (100 + k in tr.tolist())
    assert 30 <= len(te) <= 50
    with pytest.raises(ValueError, match="split must be one of"):
        split(m, "random")


def test_coverage_of_a_gaussian_error_with_its_own_sigma():
    g = torch.Generator().manual_seed(1)
    s = torch.rand(4000, 3, generator=g, dtype=F64) + 0.5
    e = torch.randn(4000, 3, generator=g, dtype=F64) * s
    c = coverage(e, s)
    assert c["share_within_3"] == pytest.approx(0.9973**3, abs=0.006)
    assert c["median_ratio"] == pytest.approx(0.674, abs=0.03)
    assert coverage(e, s / 5)["share_within_3"] < 0.5


@pytest.mark.slow
def test_real_series_c_kinematic_grouped_split_is_covered():
    data = Path(os.environ.get("TORCHCAL_IPA_DATA", DEFAULT_DATA))
    if not (data / "Series_C").is_dir():
        pytest.skip(f"ur10-ipa data (Series_C) not found at {data}; set TORCHCAL_IPA_DATA")
    res, _ = run_script(
        "trust_coverage.py", str(data), "--series", "C", "--split", "grouped", "--method", "kinematic", "--json"
    )
    assert res["n_test"] > 400 and res["rows_geometric"] == 0
    assert res["share_within_3"] >= 0.95 and 0.3 <= res["median_ratio"] <= 1.5, res
    assert res["before"]["share_within_3"] < 0.5  # the parameters alone: a kinematic run's error is its model's
