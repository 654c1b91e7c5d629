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
