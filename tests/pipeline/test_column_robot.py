"""A construction robot as its vendor describes it (a UR10 on a lifting column whose upper segment follows the
middle one as a URDF mimic joint; tests/robot/data/column_ur10.urdf) end to end through the command line: loaded as
written, simulated, calibrated with the closed loop, predicted, compensated in the controller's readings and
exported."""

import csv
import json
from pathlib import Path

import pytest
import torch

import torchcal
from torchcal.cli import main
from torchcal.data import read_measurements
from torchcal.robot import load_robot
from torchcal.sim import SimConfig, simulate

ROBOT = str(Path(__file__).resolve().parents[1] / "robot" / "data" / "column_ur10.urdf")
SIM = ["--seed", "2", "--poses", "200", "--test-poses", "80"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("column")
    sim = ["simulate", "--robot", ROBOT, "--out", str(root / "sim"), *SIM, "--effect", "compliance:3=50um"]
    assert main([*sim, "--quiet"]) == 0
    assert (
        main(["calibrate", str(root / "sim" / "train.csv"), "--robot", ROBOT, "--out", str(root / "run"), "--quiet"])
        == 0
    )
    test = root / "sim" / "test.csv"
    assert main(["predict", str(root / "run"), str(test), "--out", str(root / "pred.csv"), "--quiet"]) == 0
    return root


def test_the_vendor_description_loads_with_one_reading_for_the_column():
    robot = load_robot(ROBOT)
    assert (robot.dof, robot.n_joints) == (7, 8)
    assert robot.joint_types[0] == "prismatic" and robot.geometry.joint_types[:2] == ("prismatic", "prismatic")
    q = torch.zeros(2, 7, dtype=torch.float64)
    q[1, 0] = 0.25
    with torch.no_grad():
        rise = robot.probe_in_base(q)[1] - robot.probe_in_base(q)[0]
    torch.testing.assert_close(rise, torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64))  # both segments move


@pytest.mark.slow
def test_the_loop_names_the_compliance_and_reaches_the_noise_floor(run):
    report = json.loads((run / "run" / "report.json").read_text())
    assert [e["name"] for e in report["effects"]] == ["compliance:3"]
    test = read_measurements(run / "sim" / "test.csv", dof=7)
    pred = read_measurements(run / "pred.csv", require_positions=True, dof=7)
    got = float((pred.p - test.p).norm(dim=1).square().mean().sqrt())
    campaign = simulate(SimConfig(robot=ROBOT, seed=2, poses=200, test_poses=80))
    with torch.no_grad():  # the noise floor: the simulation's own model (without the compliance) on the test poses
        floor = float(
            (campaign.model(torchcal.effects.Context(q=campaign.test.q)) - test.p).norm(dim=1).square().mean().sqrt()
        )
    assert got <= 1.2 * max(floor, 15e-6 * 3**0.5)


def test_compensate_writes_the_controllers_seven_readings(run, tmp_path):
    targets = tmp_path / "targets.csv"
    test = read_measurements(run / "sim" / "test.csv", dof=7)
    with targets.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x", "y", "z"])
        for p in test.p[:10].tolist():
            w.writerow(p)
    out = tmp_path / "joints.csv"
    assert main(["compensate", str(run / "run"), str(targets), "--out", str(out), "--quiet"]) == 0
    rows = list(csv.DictReader(line for line in out.open() if not line.startswith("#")))
    assert len(rows) == 10 and all(f"q{k}" in rows[0] for k in range(1, 8)) and "q8" not in rows[0]
    lo, hi = load_robot(ROBOT).limits[0].tolist()
    assert all(lo - 1e-9 <= float(r["q1"]) <= hi + 1e-9 for r in rows)  # the column's reading, in metres


def test_the_calibrated_urdf_keeps_the_mimic_segment(run):
    urdf = (run / "run" / "robot_calibrated.urdf").read_text()
    assert urdf.count("<mimic") == 1 and 'type="prismatic"' in urdf
    again = load_robot(run / "run" / "robot_calibrated.urdf")
    assert (again.dof, again.n_joints) == (7, 8)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["pcm", "kinematic+ann", "integrated"])
def test_every_method_calibrates_the_column_robot_on_a_trajectory(method):
    from torchcal._threads import torch_threads
    from torchcal.pipeline import Options, calibrate

    c = simulate(SimConfig(robot=ROBOT, trajectory=True, samples=600, train_samples=480, seed=1))
    with torch_threads(1):
        run = calibrate(ROBOT, c.train, Options(method=method, seed=1))
    st = {s.name: s.rmse for s in run.stages}
    assert run.robot.dof == 7 and run.stages[-1].rmse <= st["nominal"]
    if method != "pcm":  # the kinematic calibration fits the column's and the arm's geometry through the mimic
        assert st["geometric"] < 0.5 * st["nominal"]
