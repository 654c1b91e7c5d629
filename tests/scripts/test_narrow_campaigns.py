"""scripts/narrow_campaigns.py: beyond the joints a narrow campaign saw, each method against the nominal robot."""

import pytest
from _cli import run_script


@pytest.mark.slow
def test_a_narrow_campaign_is_predicted_no_worse_than_the_nominal_robot_and_its_sigma_covers():
    res, _ = run_script("narrow_campaigns.py", "--seeds", "1", "--poses", "150", "--test-poses", "60", "--json")
    assert [c["compliance"] is not None for c in res["campaigns"]] == [False, True]
    for c in res["campaigns"]:
        assert c["nominal"]["rmse_mm"] > 0.1  # the biased geometry shows beyond the region
        for name in ("kinematic", "default"):
            models = c[name]["models"]
            assert set(models) == {"full", "geometric", "physical", "nominal"} and sum(models.values()) == 60
            # the model the run chose beyond its region predicts every test row (all lie beyond it)
            assert c[name]["beyond"]["model"] in models and models[c[name]["beyond"]["model"]] == 60, c[name]
    comp = res["campaigns"][1]
    # the kinematic geometry must not take up the compliance with the joints the campaign held (issue 51: 7.4 mm
    # against the nominal robot's 1.0 mm on seed 1 before the tolerance prior)
    assert comp["kinematic_vs_nominal"] < 1.2, comp
    assert comp["default_vs_nominal"] < 1.0, comp
    assert comp["default"]["within_3_sigma"] >= 0.9 and comp["default"]["median_ratio"] >= 0.3, comp
