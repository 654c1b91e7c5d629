"""scripts/tool_axis.py runs and reports the held lever arm (the tool-axis case of issue 23)."""

import pytest
from _cli import run_script


@pytest.mark.slow
def test_tool_axis_script_holds_the_given_lever_arm_and_prints_json():
    res, _ = run_script("tool_axis.py", "--poses", "120", "--test-poses", "30", "--cases", "given_tool", "--json")
    case = res["cases"]["given_tool"]
    assert [h["name"] for h in case["held"]] == ["tool.z"]
    assert abs(case["tool_error_mm"][2]) < 1e-3  # held at the given (true) value
    assert res["tool_axis"]["max_deg_train_test"] <= 0.03
    assert case["turned_over_holdout"] < 3.0 and case["turned_mm"] > 0
