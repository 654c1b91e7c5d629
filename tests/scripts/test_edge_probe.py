"""scripts/edge_probe.py: a calibration probed just outside its data keeps its correction bounded there."""

import pytest
from _cli import cli_simulate, run_script


@pytest.mark.slow
def test_the_correction_beyond_the_data_stays_within_twice_its_largest_on_the_data(tmp_path):
    # a smooth field the geometry lacks: the network learns it on the poses; 0.1-0.6 rad beyond any joint's range
    # nothing says how it continues, and it must fade instead of growing
    assert cli_simulate(tmp_path / "sim", "--poses", "200", "--test-poses", "10", "--seed", "5",
                        "--effect", "field=0.1mm") == 0  # fmt: skip
    res, _ = run_script(
        "edge_probe.py", "probe", str(tmp_path / "sim" / "train.csv"), "--robot", "ur5",
        "--method", "kinematic+ann", "--per-side", "8", "--json",
    )  # fmt: skip
    assert res["n_probes"] > 40 and 0.1 <= res["extrapolation_min"] <= res["extrapolation_max"] <= 0.6
    assert res["max_correction_train_mm"] > 0.01  # the network corrects something on the poses
    assert res["ratio"] <= 2.0, res
    # 0.4-0.6 rad out the correction has faded to the geometry (a network alone would keep about all of it)
    far = res["max_correction_by_distance_mm"]["0.4-0.61"]
    assert far < 0.15 * res["max_correction_train_mm"], res
