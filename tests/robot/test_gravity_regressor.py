"""The gravity regressor against the gravity torques on every kind of chain: revolute, prismatic, mimic joints and
a readings map (``tau = Y pi`` with ``pi`` the links' mass moments), so that a lumped compliance sees the same
torques a mass-based one would."""

from pathlib import Path

import pytest
import torch

from torchcal.robot import load_robot

DATA = Path(__file__).resolve().parent / "data"
ROBOTS = [
    "ur5",
    "ur10_track",
    "arm7_dh",
    str(DATA / "column_ur10.urdf"),
    str(Path(__file__).parent / "data" / "fanuc_like.yaml"),
]


@pytest.mark.parametrize("spec", ROBOTS, ids=lambda s: Path(s).stem)
def test_the_regressor_times_the_mass_moments_is_the_gravity_torque(spec):
    robot = load_robot(spec)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():  # masses where the description has none: the identity holds for any
        robot.masses.copy_(torch.rand(robot.n_joints, generator=g, dtype=torch.float64) * 5 + 1)
        robot.coms.copy_(torch.randn(robot.n_joints, 3, generator=g, dtype=torch.float64) * 0.1)
    lo, hi = robot.limits.unbind(-1)
    q = lo + (hi - lo) * torch.rand(25, robot.dof, generator=g, dtype=torch.float64)
    pi = torch.cat([robot.masses[:, None], robot.masses[:, None] * robot.coms], dim=1).reshape(-1)
    with torch.no_grad():
        Y, tau = robot.gravity_regressor(q), robot.gravity_torques(q)
    assert Y.shape == (25, robot.dof, 4 * robot.n_joints)
    torch.testing.assert_close(Y @ pi, tau, rtol=0, atol=1e-11)
