"""plan's sampled candidates: within a run's calibrated region where given, seeded, and where the tracker sees few
poses it plans among the usable ones it found instead of asking for a candidates file."""

import pytest
import torch

from torchcal.effects import MeasurementModel
from torchcal.errors import OptionError
from torchcal.robot import load_robot
from torchcal.use import plan as P


@pytest.fixture(scope="module")
def ur5():
    return MeasurementModel(load_robot("ur5"))


def test_candidates_lie_within_the_region_and_repeat_with_the_seed(ur5):
    region = torch.tensor([[-1.0, -2.0, -1.5, -1.0, -0.5, -3.0], [1.0, -1.0, 1.5, 1.0, 0.5, 3.0]], dtype=torch.float64)
    q = P.sample_candidates(ur5, 300, 4, region=region)
    assert q.shape == (300, 6)
    assert bool((q >= region[0]).all()) and bool((q <= region[1]).all())
    assert torch.equal(q, P.sample_candidates(ur5, 300, 4, region=region))


def test_without_a_region_the_draws_are_those_of_the_joint_limits(ur5):
    q = P.sample_candidates(ur5, 200, 1)
    lo, hi = ur5.robot.limits[:, 0].clamp(min=-torch.pi), ur5.robot.limits[:, 1].clamp(max=torch.pi)
    assert bool((q >= lo).all()) and bool((q <= hi).all())
    # the region is what narrows the draws: joint 2 spreads over most of a turn without one
    assert float(q[:, 1].max() - q[:, 1].min()) > 4.0


def _rarely_seen(one_in: int):
    def visible(self, q):
        return (q[:, 0] * 1e6).floor().remainder(one_in) == 0

    return visible


def test_few_usable_poses_are_planned_among_not_refused(ur5, monkeypatch, capsys):
    monkeypatch.setattr(P.Scene, "visible", _rarely_seen(500))
    monkeypatch.setattr(P._console, "_quiet", False)  # an earlier command's --quiet stays set in the process
    q = P.sample_candidates(ur5, 10_000, 0, need=12)
    assert 12 <= len(q) < 10_000
    err = capsys.readouterr().err
    assert f"{len(q)} of {P.SAMPLE_DRAWS * 10_000}" in err and "planning among them" in err


def test_fewer_usable_poses_than_the_plan_needs_are_refused_with_the_count(ur5, monkeypatch):
    monkeypatch.setattr(P.Scene, "visible", lambda self, q: torch.zeros(len(q), dtype=torch.bool))
    with pytest.raises(OptionError, match=r"only 0 of 512 poses drawn .* fewer than the 12 the plan needs"):
        P.sample_candidates(ur5, 10, 0, need=12)


def test_a_region_outside_a_joints_limits_falls_back_to_the_limits(ur5):
    region = torch.tensor([[-1.0] * 6, [1.0] * 6], dtype=torch.float64)
    region[:, 0] = torch.tensor([7.0, 8.0])  # beyond joint 1's clipped limits: ignored for that joint
    q = P.sample_candidates(ur5, 50, 0, region=region)
    assert bool((q[:, 1:] >= -1.0).all()) and bool((q[:, 1:] <= 1.0).all())
    assert float(q[:, 0].abs().max()) <= torch.pi


@pytest.mark.slow
def test_plan_run_samples_within_the_runs_region_and_plans_among_few_usable_ones(tmp_path, monkeypatch, capsys):
    from torchcal.cli import main
    from torchcal.data import read_measurements
    from torchcal.pipeline import Options, calibrate
    from torchcal.report.rundir import write_run
    from torchcal.sim.campaign import SimConfig, simulate
    from torchcal.use.rundir import load_model

    c = simulate(SimConfig(robot="ur5", poses=80, test_poses=10, seed=1))
    rd = write_run(calibrate("ur5", c.train, Options.of(method="kinematic", seed=0, holdout=0.2)), tmp_path / "run")
    region = load_model(rd)[0].region
    monkeypatch.setattr(P.Scene, "visible", _rarely_seen(400))  # a tracker that sees one draw in 400
    out = tmp_path / "plan.csv"
    assert main(["plan", "--run", str(rd), "--n", "12", "--pool", "2000", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "within the run's calibrated region" in err and "planning among them" in err
    q = read_measurements(out, require_positions=False).q
    assert q.shape == (12, 6)
    assert bool((q >= region[0] - 1e-12).all()) and bool((q <= region[1] + 1e-12).all())
