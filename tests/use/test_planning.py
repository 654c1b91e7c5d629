"""``torchcal.use.planning``: a plan made through the library as ``torchcal plan`` makes it, without the command
line (issue 48 item 7): the setting of a robot, the sampled candidates, the poses and the plan's JSON and Markdown
beside them; a run's setting refuses another robot, naming the argument."""

import json

import pytest

from torchcal.data import read_measurements
from torchcal.errors import OptionError
from torchcal.use.plan import PlanOptions, plan_poses, sample_candidates
from torchcal.use.planning import robot_setting, run_setting, sampling_region, side_paths, write_plan


def test_a_plan_through_the_library_writes_the_poses_and_their_side_files(tmp_path):
    setting = robot_setting("ur5").with_scene(tracker=(2.0, 0.1, 0.3))
    assert setting.method == "auto" and setting.sigma_tracker == 15e-6 and setting.s0_sq == 1.0
    assert setting.tracker.tolist() == [2.0, 0.1, 0.3] and setting.lever is None
    region, within = sampling_region(setting, in_region=False)
    assert region is None and within == ""
    q = sample_candidates(setting.model, 300, 0, setting.tracker, setting.lever, need=12)
    opts = PlanOptions.for_method("kinematic", 12, sigma_tracker=setting.sigma_tracker, seed=0)
    plan = plan_poses(setting.model, q, opts)
    out = tmp_path / "poses.csv"
    side = write_plan(out, plan, robot_name="ur5", source="300 sampled", payload_levels=(0.0, 5.0))
    assert side == side_paths(out) == {"json": tmp_path / "poses.plan.json", "md": tmp_path / "poses.plan.md"}
    planned = read_measurements(out, require_positions=False)
    assert planned.n == 12 and planned.payload.tolist() == [0.0, 5.0] * 6
    summary = json.loads(side["json"].read_text())
    assert summary["written_by"] == "torchcal plan" and summary["poses"] == str(out)
    assert summary["candidates"] == "300 sampled" and summary["loads"]["rows"] == [6, 6]
    assert side["md"].read_text().startswith("# written_by: torchcal plan\n")


@pytest.mark.slow
def test_a_runs_setting_refuses_another_robot_naming_the_argument(tmp_path):
    with pytest.raises(OptionError, match="not a directory; expected a run directory"):
        run_setting(tmp_path / "none")
    from tests._cli import cli_simulate
    from torchcal.cli import main

    assert cli_simulate(tmp_path / "sim", "--poses", "40", "--test-poses", "5") == 0
    run = tmp_path / "run"
    data = tmp_path / "sim" / "train.csv"
    assert main(["calibrate", str(data), "--robot", "ur5", "--method", "kinematic", "--out", str(run), "--quiet"]) == 0
    setting = run_setting(run)
    assert setting.method == "kinematic" and setting.tracker is not None and setting.lever is not None
    with pytest.raises(OptionError, match=r"robot ur10 \(--robot\) is not the robot of the run"):
        run_setting(run, robot="ur10")
