"""scripts/any_robot.py: the four kinds of cell of docs/robots.md, one small campaign each way."""

import pytest

from experiments import any_robot
from torchcal._threads import torch_threads


@pytest.mark.parametrize("name", ["column", "arm7_differential"])
def test_a_case_measures_the_run_against_the_true_structure_and_the_floor(name):
    with torch_threads(1):
        out = any_robot.run([name], [1], poses=160, clean=False)
    (row,) = out["rows"]
    assert row["readings"] == 7 and row["model_joints"] == (8 if name == "column" else 7)
    assert row["test_oracle_mm"] <= row["test_true_structure_mm"] <= row["test_geometric_mm"]
    assert 0.9 < row["ratio_to_true_structure"] < 1.5 and out["clean_named"] == []
    if name == "arm7_differential":  # the differential's ratio error, estimated within a few of its sigmas
        assert abs(row["z"]["readings.c6_6"]) < 4
