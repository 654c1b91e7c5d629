"""``torchcal locate``: the instrument's rough pose from a few points at nominal poses, against the truth."""

import json
import math

import pytest
import torch

from tests._cli import cli_simulate
from torchcal.cli import main
from torchcal.data import read_measurements
from torchcal.errors import EstimationError
from torchcal.robot import load_robot
from torchcal.use.locate import locate


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    out = tmp_path_factory.mktemp("locate") / "cell"
    assert cli_simulate(out, "--poses", "30", "--test-poses", "5", "--seed", "3") == 0
    truth = json.loads((out / "truth.json").read_text())
    return out, truth


def _first(cell, n, tmp_path):
    out, _ = cell
    lines = (out / "train.csv").read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#") or ln.startswith("q1")]
    rows = [ln for ln in lines if not (ln.startswith("#") or ln.startswith("q1"))]
    path = tmp_path / f"first{n}.csv"
    path.write_text("\n".join(head + rows[:n]) + "\n")
    return path


def _tracker_truth(truth):
    return [v * 1e3 for v in truth["instrument"]["tracker_in_base_m"]]


def test_six_points_fit_the_lever_arm_and_find_the_tracker_within_millimetres(cell, tmp_path):
    robot = load_robot("ur5")
    data = read_measurements(_first(cell, 6, tmp_path), dof=6)
    found = locate(robot, data.q, data.p)
    assert found.lever_fitted and found.n == 6
    truth = cell[1]
    assert math.dist([float(v) * 1e3 for v in found.tracker_in_base()], _tracker_truth(truth)) < 5.0
    true_lever = [v * 1e3 for v in truth["tool"]["t_flange_probe"]]
    assert math.dist([float(v) * 1e3 for v in found.lever], true_lever) < 2.0


def test_three_points_hold_the_nominal_lever_arm_and_fitting_it_is_refused(cell, tmp_path):
    robot = load_robot("ur5")
    data = read_measurements(_first(cell, 3, tmp_path), dof=6)
    found = locate(robot, data.q, data.p)
    assert not found.lever_fitted
    assert torch.allclose(found.lever, torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64))
    with pytest.raises(EstimationError, match="four or more points"):
        locate(robot, data.q, data.p, fit_lever=True)
    with pytest.raises(EstimationError, match="three or more points"):
        locate(robot, data.q[:2], data.p[:2])


def test_the_command_prints_what_plan_takes_and_rewrites_its_own_json(cell, tmp_path, capsys):
    points = _first(cell, 6, tmp_path)
    out = tmp_path / "where.json"
    assert main(["locate", str(points), "--robot", "ur5", "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    xyz = [float(v) for v in printed.split(",")]
    assert math.dist(xyz, _tracker_truth(cell[1])) < 5.0
    saved = json.loads(out.read_text())
    assert saved["written_by"] == "torchcal locate" and saved["lever_fitted"] is True
    assert main(["locate", str(points), "--robot", "ur5", "--out", str(out), "--quiet"]) == 0  # its own file


def test_two_points_are_refused_naming_the_file(cell, tmp_path, capsys):
    points = _first(cell, 2, tmp_path)
    assert main(["locate", str(points), "--robot", "ur5"]) == 2
    err = capsys.readouterr().err
    assert str(points) in err and "locating the instrument" in err
