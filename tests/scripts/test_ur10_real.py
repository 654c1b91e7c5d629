"""scripts/ur10_real.py on the real UR10 data (--quick): calibration helps, and the C geometry carries over to B."""

import json
import os
from pathlib import Path

import pytest
from _cli import run_script

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "real" / "ur10-ipa"


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    data = Path(os.environ.get("TORCHCAL_IPA_DATA", DEFAULT_DATA))
    if not (data / "Series_B").is_dir() or not (data / "Series_C").is_dir():
        pytest.skip(f"ur10-ipa data (Series_B and Series_C) not found at {data}; set TORCHCAL_IPA_DATA")
    out = tmp_path_factory.mktemp("ur10")
    res, _ = run_script("ur10_real.py", str(data), "--quick", "--json", "--threads", "1", "--out", str(out))
    return res, out


@pytest.mark.slow
def test_quick_writes_both_files_and_the_json_line(quick):
    res, out = quick
    assert json.loads((out / "ur10_real.json").read_text())["within"] == res["within"]
    md = (out / "ur10_real.md").read_text()
    assert "## Part 1" in md and "## Part 2" in md and "C → B" in md
    assert "kept on one side (grouped)" in md


@pytest.mark.slow
def test_series_c_kinematic_calibration_beats_nominal(quick):
    res, _ = quick
    (row,) = [r for r in res["within"] if r["series"] == "C" and r["method"] == "kinematic"]
    assert row["n_holdout"] == round(0.2 * (row["n_train"] + row["n_holdout"]))
    # calibrate's grouped split; Series C measures no configuration twice, so no group was merged
    assert row["split"]["grouped"] and row["split"]["merged_groups"] == 0
    assert row["cpu_s"] > 0
    # measured 0.494 mm after vs 1.035 mm nominal (tracker pose and lever arm fitted in both)
    assert row["final"]["rmse_mm"] < 0.55
    assert row["final"]["rmse_mm"] < 0.6 * row["nominal"]["rmse_mm"]


def test_c_to_b_transfer_beats_nominal_geometry(quick):
    res, _ = quick
    (t,) = [t for t in res["transfer"] if (t["source"], t["target"]) == ("C", "B")]
    assert t["n_fit"] + t["n_eval"] == 1495
    # measured 0.945 mm with the C geometry vs 1.088 mm nominal, both with the tracker re-fitted on 20 % of B
    assert t["transferred_refit"]["rmse_mm"] < t["nominal_refit"]["rmse_mm"]
    assert t["no_refit"] is not None  # B and C share the tracker placement
