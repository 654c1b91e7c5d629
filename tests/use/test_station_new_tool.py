"""station without --tool after the tool changed: the points fit worse than the run predicts with its lever arm, so
station tests a new lever arm, fits it where the points then fit as predicted and says so; its predicted error then
covers the error measured at the other rows."""

import pytest
import torch

from torchcal.effects import Context
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.sim.campaign import SimConfig, simulate
from torchcal.use.rundir import load_model
from torchcal.use.station import restation

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    c = simulate(SimConfig(robot="ur5", poses=160, test_poses=60, seed=5))
    run = calibrate("ur5", c.train, Options.of(method="kinematic", seed=0, holdout=0.25, trajectory=False))
    rd = write_run(run, tmp_path_factory.mktemp("tool") / "run")
    model, _ = load_model(rd)
    test = c.test
    with torch.no_grad():  # the tool moved 20 mm in the flange frame: each row's probe moves with the flange's rotation
        T = model.robot.T_tracker_base() @ model.robot(test.q)
        dt = torch.tensor([0.012, -0.010, 0.012], dtype=torch.float64)
        moved = test.with_positions(test.p + (T[:, :3, :3] @ dt))
    return {"run": rd, "points": moved.subset(range(10)), "rest": moved.subset(range(10, moved.n)), "dt": dt}


def test_a_changed_tool_is_found_and_fitted(setup):
    model, _, station = restation(setup["run"], setup["points"])
    assert station.tool and station.chi_square["passed"]
    assert "the tool changed" in station.warnings[0]
    run_model, _ = load_model(setup["run"])
    moved_by = station.t_flange_probe - run_model.robot.t_flange_probe()
    assert torch.allclose(moved_by, setup["dt"], atol=3e-4), moved_by
    rest = setup["rest"]
    with torch.no_grad():
        measured = float((model(Context(q=rest.q)) - rest.p).norm(dim=1).square().mean().sqrt())
    print(f"predicted {station.predicted_rmse * 1e3:.4f} mm, measured {measured * 1e3:.4f} mm")
    assert measured < 1e-4  # 0.1 mm: the lever arm found; with the old one every row is 20 mm off
    assert measured / 1.5 < station.predicted_rmse < 1.5 * measured, (station.predicted_rmse, measured)


def test_points_of_the_old_tool_keep_its_lever_arm(setup, tmp_path):

    c = simulate(SimConfig(robot="ur5", poses=160, test_poses=60, seed=5))
    _, _, station = restation(setup["run"], c.test.subset(range(10)))
    assert not station.tool and station.chi_square["passed"]
