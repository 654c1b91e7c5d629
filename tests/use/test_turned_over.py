"""Poses whose tool is turned beyond the orientations a run saw are flagged like joints beyond its region: a run whose
tool axis kept within a cone (a lifting-column robot measured by a total station) records that cone in model.json, and
predict's extrapolation column and stderr name every row beyond it, whatever its joints."""

import csv
import json
import math

import pytest
import torch

from torchcal.cli import main
from torchcal.data import write_measurements
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.sim.campaign import SimConfig, simulate
from torchcal.use.rundir import load_model, tool_axis_beyond, tool_axis_cone

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    c = simulate(SimConfig(robot="ur5", poses=120, test_poses=40, seed=2, tool_axis_deg=10.0))
    run = calibrate("ur5", c.train, Options.of(method="kinematic", seed=0, holdout=0.25, trajectory=False))
    return {"campaign": c, "run": write_run(run, tmp_path_factory.mktemp("turned") / "run")}


def test_the_run_records_its_tool_axis_cone(setup):
    cone = json.loads((setup["run"] / "model.json").read_text())["tool_axis"]
    assert 0 < cone["max_angle"] <= torch.pi / 18 + 1e-6  # the campaign's 10 deg spread
    assert abs(sum(v * v for v in cone["axis"]) - 1) < 1e-12


def test_every_turned_row_is_flagged_and_the_rows_within_the_cone_are_not(setup, tmp_path, capsys):
    c = setup["campaign"]
    model, _ = load_model(setup["run"])
    # turned at least 30 deg off the campaign's axis, whose cone is 10 deg: every one at least 15 deg beyond
    assert float(tool_axis_beyond(model, c.turned.q).min()) > math.radians(15)
    # rows like the calibration's (its held-out and test rows) lie within it or a hair beyond, as joints do
    assert float(tool_axis_beyond(model, c.test.q).max()) < math.radians(1)
    f = tmp_path / "turned.csv"
    write_measurements(f, c.turned)
    assert main(["predict", str(setup["run"]), str(f), "--out", str(tmp_path / "p.csv")]) == 0
    err = capsys.readouterr().err
    with open(tmp_path / "p.csv") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    assert len(rows) == c.turned.n and all(float(r["extrapolation"]) > 0 for r in rows)
    assert "tool axis lies" in err or "beyond the calibrated region" in err


def test_a_cone_of_every_direction_flags_nothing():
    from torchcal.robot import load_robot

    robot = load_robot("ur5")
    q = torch.rand(400, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 6.28 - 3.14
    assert tool_axis_cone(robot, q) is None
