"""scripts/load_extrapolation.py runs and prints the issue-45 targets as JSON (a small torque campaign)."""

import pytest
from _cli import run_script


@pytest.mark.slow  # two small calibrations
def test_load_extrapolation_script_prints_targets():
    res, _ = run_script("load_extrapolation.py", "--poses", "60", "--parts", "torques", "--json")
    per_load = res["torques"]["per_load"]
    assert set(per_load) == {"5kg", "10kg"}
    for row in per_load.values():
        assert row["oracle_mm"] > 0 and row["default"]["flagged"] == 1.0
        assert row["kinematic"]["rmse_mm"] > row["default"]["rmse_mm"]  # the kinematic run cannot carry the load
    assert set(res["targets"]) == {
        "torques: ratio_to_oracle <= 1.2",
        "torques: default not worse than kinematic",
        "torques: >= 95 % within 3 sigma",
    }
