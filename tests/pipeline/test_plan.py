"""``torchcal plan`` (torchcal.pipeline.plan): the command end to end into a calibration, and the predicted held-out
error against the measured one on a simulated campaign."""

import json

import pytest
import torch

from torchcal.cli import main
from torchcal.data import Measurements, read_measurements, write_measurements
from torchcal.effects import Context
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.experiments.plan_poses import compare
from torchcal.pipeline.plan import PlanOptions, plan_poses
from torchcal.robot import load_robot
from torchcal.sim import SimConfig, simulate
from torchcal.sim.poses import sample_joints


@pytest.fixture(scope="module")
def campaign():
    return simulate(SimConfig(robot="ur5", poses=1500, test_poses=300, seed=3))


def test_plan_end_to_end_into_calibrate(campaign, tmp_path):
    cand = tmp_path / "candidates.csv"
    write_measurements(cand, campaign.train)
    out = tmp_path / "plan" / "poses.csv"
    assert main(["plan", "--robot", "ur5", "--candidates", str(cand), "--n", "40", "--out", str(out), "--quiet"]) == 0
    planned = read_measurements(out, dof=6, require_positions=False)
    assert planned.n == 40 and planned.p is None
    # every planned pose is one of the candidates (bit-identical: the files are written with repr)
    rows = {tuple(r) for r in campaign.train.q.tolist()}
    assert all(tuple(r) in rows for r in planned.q.tolist())
    summary = json.loads((tmp_path / "plan" / "poses.plan.json").read_text())
    assert summary["k"] == 40 and summary["n_candidates"] == 1500
    assert [c["k"] for c in summary["curve"]][-1] == 80
    assert summary["predicted_holdout_rmse_mm"] > 0 and summary["parameters"]
    assert (tmp_path / "plan" / "poses.plan.md").read_text().startswith("# written_by: torchcal plan")
    # measure the planned poses with the simulator's true model, then calibrate them
    with torch.no_grad():
        p = campaign.model(Context(q=planned.q)) + 15e-6 * torch.randn(
            40, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64
        )
    meas = tmp_path / "measured.csv"
    write_measurements(meas, Measurements(q=planned.q, p=p))
    run = tmp_path / "run"
    assert main(["calibrate", str(meas), "--robot", "ur5", "--method", "kinematic", "--out", str(run), "--quiet"]) == 0
    # plan again over the same file: its own earlier outputs are replaced without --force
    assert main(["plan", "--robot", "ur5", "--candidates", str(cand), "--n", "10", "--out", str(out), "--quiet"]) == 0
    # and with the run: its model and stochastic model, sampled candidates
    out2 = tmp_path / "again.csv"
    code = main(["plan", "--run", str(run), "--n", "20", "--pool", "500", "--out", str(out2), "--quiet"])
    assert code == 0 and read_measurements(out2, dof=6, require_positions=False).n == 20


def test_plan_refuses_what_it_cannot_do(tmp_path):
    assert main(["plan", "--n", "5", "--out", str(tmp_path / "x.csv"), "--quiet"]) == 2  # no robot
    model = MeasurementModel(load_robot("ur5"))
    q = sample_joints(model.robot, 50, torch.Generator().manual_seed(0))
    with pytest.raises(OptionError, match="1 to 50"):
        plan_poses(model, q, PlanOptions(k=51))
    with pytest.raises(OptionError, match="edge_share"):
        plan_poses(model, q, PlanOptions(k=5, edge_share=0.7))


def test_edge_share_is_kept(campaign):
    model = MeasurementModel(load_robot("ur5"))
    plan = plan_poses(model, campaign.train.q, PlanOptions(k=50, edge_share=0.2))
    assert int(plan.edge[4::5].sum()) == 10  # every fifth pick is an edge pose


def test_predicted_holdout_error_within_25_percent(campaign):
    res = compare("ur5", campaign.train, campaign.test, (30, 100), seeds=1, reference=None)
    for row in res["sizes"]:
        print(row["k"], row["planned_mm"], row["predicted_mm"], row["random_mm"]["median"])
        assert 0.75 < row["predicted_over_measured"] < 1.25, row
