"""scripts/ur10_orientation.py (experiments.ur10_orientation): position-only against full-pose calibration
on the real UR10 Series D (ISO cubes, 632 poses) when the ur10-ipa data are present."""

import os
from pathlib import Path

import pytest
from _cli import run_script

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "real" / "ur10-ipa"


@pytest.mark.slow
def test_series_d_full_pose_against_position_only():
    data = Path(os.environ.get("TORCHCAL_IPA_DATA", DEFAULT_DATA))
    if not (data / "Series_D").is_dir():
        pytest.skip(f"ur10-ipa data not found at {data} (set TORCHCAL_IPA_DATA to its folder)")
    res, stderr = run_script("ur10_orientation.py", str(data), "--series", "D", "--json", timeout=240)
    (r,) = res["results"]
    po, fp = r["position_only"], r["full_pose"]
    assert r["orientation_sigma"] == "per row" and po["n_holdout"] == fp["n_holdout"]  # one split for both
    # the orientation is fitted: better than nominal and than the position-only geometry
    assert fp["final"]["orientation"]["rmse_deg"] < fp["nominal"]["orientation"]["rmse_deg"]
    assert fp["final"]["orientation"]["rmse_deg"] < po["final"]["orientation"]["rmse_deg"]
    # and the position stays within 5 % of the position-only fit's
    assert fp["final"]["rmse_mm"] < 1.05 * po["final"]["rmse_mm"]
    assert "| D | kinematic |" in stderr
