"""station as its help says: points whose ``station`` column names a new placement re-station the run under that name
(predict then takes rows of that name, and refuses the run's old ones), and the predicted error is over poses like the
points, within a factor 2 of the error measured there."""

import csv
import dataclasses

import pytest
import torch

from torchcal.cli import main
from torchcal.data import write_measurements
from torchcal.effects import Context
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.sim.campaign import SimConfig, simulate
from torchcal.use.station import points_region, restation

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    c = simulate(SimConfig(robot="ur5", poses=160, test_poses=60, seed=3, stations=2))
    root = tmp_path_factory.mktemp("newplace")
    run = calibrate("ur5", c.train, Options.of(method="kinematic", seed=0, holdout=0.25, trajectory=False))
    rd = write_run(run, root / "run")
    test = c.test
    second = test.subset(torch.nonzero(test.station == 1).flatten())  # one placement's rows, named 'newplace'
    named = dataclasses.replace(second, station=torch.zeros_like(second.station), station_names=("newplace",))
    return {"run": rd, "points": named.subset(range(10)), "rest": named.subset(range(10, named.n)), "root": root}


def test_points_naming_a_new_placement_are_restationed_under_that_name(setup, tmp_path, capsys):
    pts, rest = tmp_path / "pts.csv", tmp_path / "rest.csv"
    write_measurements(pts, setup["points"])
    write_measurements(rest, setup["rest"])
    assert main(["station", str(setup["run"]), str(pts), "--out", str(tmp_path / "st"), "--quiet"]) == 0
    assert main(["predict", str(tmp_path / "st"), str(rest), "--out", str(tmp_path / "p.csv"), "--quiet"]) == 0
    with open(tmp_path / "p.csv") as f:
        rows = [r for r in csv.DictReader(line for line in f if not line.startswith("#"))]
    assert len(rows) == setup["rest"].n and {r["station"] for r in rows} == {"newplace"}
    pred = torch.tensor([[float(r[k]) for k in "xyz"] for r in rows], dtype=torch.float64)
    measured = float((pred - setup["rest"].p).norm(dim=1).square().mean().sqrt())
    _, _, station = restation(setup["run"], setup["points"])
    assert station.label == "newplace"
    print(f"predicted {station.predicted_rmse * 1e3:.4f} mm, measured {measured * 1e3:.4f} mm")
    assert measured / 2 < station.predicted_rmse < 2 * measured, (station.predicted_rmse, measured)


def test_the_predicted_error_is_over_poses_like_the_points(setup):
    model, _, station = restation(setup["run"], setup["points"])
    region = points_region(model, setup["points"])
    q = setup["points"].q
    assert torch.equal(region[0], torch.maximum(q.min(0).values, model.region[0]))
    assert torch.equal(region[1], torch.minimum(q.max(0).values, model.region[1]))
    # a joint the points hold still: no spread there
    held = setup["points"].q.clone()
    held[:, 5] = 0.3
    pts = dataclasses.replace(setup["points"], q=held)
    r = points_region(model, pts)
    assert float(r[0, 5]) == float(r[1, 5]) == 0.3


def test_a_held_lever_arm_component_does_not_inflate_the_predicted_error(tmp_path):
    """A campaign whose tool axis never turns (each station's axis faces its instrument) cannot see the lever arm
    along it: the run holds that component at its prior. Re-stationed on 10 points naming a new placement, the
    predicted error is that of predict's sigma with the placement's correlation to the held component (which it
    absorbs at poses like the points): within 2x of the error measured at the placement's other rows, where the
    placement's sigma alone is mm."""
    c = simulate(SimConfig(robot="ur5", poses=240, test_poses=80, seed=3, stations=2, tool_axis_deg=0.03))
    run = calibrate("ur5", c.train, Options.of(method="kinematic", seed=0, holdout=0.25, trajectory=False))
    rd = write_run(run, tmp_path / "run")
    second = c.test.subset(torch.nonzero(c.test.station == 1).flatten())
    named = dataclasses.replace(second, station=torch.zeros_like(second.station), station_names=("newplace",))
    model, _, station = restation(rd, named.subset(range(10)))
    rest = named.subset(range(10, named.n))
    with torch.no_grad():
        measured = float((model(Context(q=rest.q)) - rest.p).norm(dim=1).square().mean().sqrt())
    print(
        f"predicted {station.predicted_rmse * 1e3:.4f} mm, measured {measured * 1e3:.4f} mm, placement sigma alone "
        f"{station.region_sigma_rms * 1e3:.4f} mm"
    )
    assert station.region_sigma_rms > 10 * measured  # what the prediction was before: the held prior spread
    assert measured / 2 < station.predicted_rmse < 2 * measured
