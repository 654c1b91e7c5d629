"""Closed-form rigid fit and tracker-pose + lever-arm fit: noise-free recovery."""

import pytest
import torch

import torchcal
from torchcal.errors import EstimationError
from torchcal.estimate import fit_instrument_and_tool, rigid_fit
from torchcal.robot import transforms as tf
from torchcal.sim import SimConfig, simulate

F64 = torch.float64


def test_rigid_fit_recovers_a_known_transform():
    g = torch.Generator().manual_seed(0)
    T = tf.se3_from_vector(torch.tensor([1.0, -2.0, 0.5, 0.3, -1.2, 2.9], dtype=F64))
    p = torch.randn(50, 3, generator=g, dtype=F64)
    T_hat = rigid_fit(p, tf.transform_points(T, p))
    assert (T_hat - T).abs().max() < 1e-13


def test_rigid_fit_refuses_collinear_points():
    p = torch.linspace(0, 1, 10, dtype=F64)[:, None] * torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    with pytest.raises(EstimationError, match="collinear"):
        rigid_fit(p, p)


def test_instrument_and_lever_arm_recovered_without_noise():
    c = simulate(
        SimConfig(
            robot="ur10",
            poses=100,
            test_poses=0,
            seed=2,
            sigma_tracker=0.0,
            sigma_joint_deg=0.0,
            sigma_length=0.0,
            sigma_angle_deg=0.0,
        )
    )
    robot = torchcal.load_robot("ur10")
    with torch.no_grad():
        T, lever, rms = fit_instrument_and_tool(robot(c.train.q), c.train.p)
    truth = c.truth
    assert (T - torch.tensor(truth["instrument"]["T_tracker_base"], dtype=F64)).abs().max() < 1e-9
    assert (lever - torch.tensor(truth["tool"]["t_flange_probe"], dtype=F64)).abs().max() < 1e-9
    assert rms < 1e-9


def test_lever_arm_prior_fixes_what_a_still_flange_leaves_open():
    # every pose has the same flange orientation: the lever arm and the tracker's position cannot be told apart,
    # the least-squares step is singular; the prior's ridge puts the lever arm at its centre, and the fit is exact
    g = torch.Generator().manual_seed(3)
    n = 40
    T_bf = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T_bf[:, :3, 3] = torch.rand(n, 3, generator=g, dtype=torch.float64)
    t_true = torch.tensor([0.01, -0.02, 0.1], dtype=torch.float64)
    p = T_bf[:, :3, 3] + t_true + torch.tensor([2.0, 0.5, -0.3], dtype=torch.float64)
    centre = torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64)
    T, t, rms = fit_instrument_and_tool(T_bf, p, centre, lever_prior=(centre, 1e-6))
    assert torch.allclose(t, centre, atol=1e-7, rtol=0)  # the ridge is 1e-6 of a 40-row normal matrix
    assert rms < 1e-9
    assert torch.allclose(T[:3, 3], torch.tensor([2.0, 0.5, -0.3], dtype=torch.float64) + t_true - centre, atol=1e-7)
