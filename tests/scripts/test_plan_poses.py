"""scripts/plan_poses.py: planned against random poses on the real UR10 (skipped without the data)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from _cli import run_script

ROOT = Path(__file__).resolve().parents[2]
IPA = Path(os.environ.get("TORCHCAL_IPA_DATA", ROOT.parent / "shared" / "data" / "real" / "ur10-ipa"))


@pytest.mark.slow
@pytest.mark.skipif(not (IPA / "Series_A").is_dir(), reason=f"ur10-ipa data not found at {IPA}; set TORCHCAL_IPA_DATA")
def test_planned_30_poses_on_series_a_and_the_predicted_error():
    res, _ = run_script("plan_poses.py", str(IPA), "--k", "30", "--seeds", "1", "--reference", "0", "--json")
    (row,) = res["sizes"]
    assert res["n_pool"] > 9000 and res["criterion"] == "I"
    # measured 0.481 mm (random 30: 0.47-0.63 mm over 5 seeds; 200 random 0.449 mm), predicted 0.450 mm
    assert row["planned_mm"] < 0.52, row
    assert 0.75 < row["predicted_over_measured"] < 1.25, row


@pytest.mark.slow
def test_a_missing_folder_is_a_usage_error(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "plan_poses.py"), str(tmp_path / "nowhere")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert proc.returncode == 2 and "data folder not found" in proc.stderr


@pytest.mark.slow
def test_a_sequential_plan_needs_one_size_above_its_first_campaign(tmp_path):
    (tmp_path / "Series_A").mkdir()
    for extra in (["--k", "100,500", "--sequential", "50"], ["--k", "100", "--sequential", "100"]):
        proc = subprocess.run(
            [sys.executable, str(ROOT / "scripts" / "plan_poses.py"), str(tmp_path), *extra],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        assert proc.returncode == 2 and "--sequential takes the real data and one --k above it" in proc.stderr
