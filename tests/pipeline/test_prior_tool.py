"""A calibration from a prior run after the tool changed: the lever arm is released as one vector, not a component at
a time while the rest of a 20 mm change goes into the wrist's elements until the fit is refused as implausible."""

import pytest
import torch

from torchcal.effects import Context
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.sim import SimConfig, simulate
from torchcal.use.rundir import load_model, load_prior

pytestmark = pytest.mark.slow


def test_a_changed_tool_is_released_whole(tmp_path):
    c = simulate(SimConfig(robot="ur10", poses=160, test_poses=70, seed=1))
    rd = write_run(calibrate("ur10", c.train, Options.of(method="kinematic", seed=1)), tmp_path / "run")
    dt = torch.tensor([0.012, -0.010, 0.013], dtype=torch.float64)
    with torch.no_grad():
        R = (c.model.robot.T_tracker_base() @ c.model.robot(c.test.q))[:, :3, :3]
    moved = c.test.with_positions(c.test.p + R @ dt)
    rows, rest = moved.subset(range(10)), moved.subset(range(10, moved.n))
    upd = calibrate(
        "ur10", rows, Options.of(method="kinematic", seed=1, trajectory=False, refit=True), prior=load_prior(rd)
    )
    before, _ = load_model(rd)
    change = upd.model.robot.t_flange_probe().detach() - before.robot.t_flange_probe()
    assert torch.allclose(change, dt, atol=1e-3), change
    assert {"tool.x", "tool.y", "tool.z"} <= set(upd.prior_update.released)
    with torch.no_grad():
        e = upd.model(Context.from_measurements(rest, trajectory=False)) - rest.p
    assert float(e.norm(dim=1).square().mean().sqrt()) < 2e-4  # 20 mm off with the old lever arm
