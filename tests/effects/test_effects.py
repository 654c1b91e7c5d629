"""Effect modules: each one's formula, and the composite measurement model."""

import math

import torch

import torchcal
from torchcal.effects import (
    Backlash,
    Compliance,
    Context,
    CorrectionNet,
    Cyclic,
    Drift,
    LearnedEffect,
    MeasurementModel,
    motion_direction,
)
from torchcal.robot import transforms as tf

F64 = torch.float64


def _q(n=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 6, generator=g, dtype=F64) * 2 - 1) * math.pi


def test_compliance_is_k_times_gravity_torque():
    robot = torchcal.load_robot("ur10")
    q = _q()
    e = Compliance(2, k=2e-6)
    dq = e(robot, Context(q=q))
    assert torch.allclose(dq[:, 1], 2e-6 * robot.gravity_torques(q)[:, 1], rtol=0, atol=1e-18)
    assert (dq[:, [0, 2, 3, 4, 5]] == 0).all()


def test_backlash_follows_torque_sign_or_motion():
    robot = torchcal.load_robot("ur5")
    q = _q()
    e = Backlash(2, b=1e-4, source="torque")
    dq = e(robot, Context(q=q))[:, 1]
    sign = torch.sign(robot.gravity_torques(q)[:, 1])
    assert torch.allclose(dq, 0.5e-4 * sign)
    direction = torch.ones_like(q)
    direction[::2] = -1
    dq = Backlash(2, b=1e-4, source="auto")(robot, Context(q=q, direction=direction))[:, 1]
    assert torch.allclose(dq, 0.5e-4 * direction[:, 1])


def test_cyclic_formula():
    robot = torchcal.load_robot("ur5")
    q = _q()
    e = Cyclic(4, harmonics=(1, 2), a=[1e-4, 2e-5], b=[-3e-5, 4e-5])
    dq = e(robot, Context(q=q))[:, 3]
    th = q[:, 3]
    ref = 1e-4 * torch.sin(th) + 2e-5 * torch.sin(2 * th) - 3e-5 * torch.cos(th) + 4e-5 * torch.cos(2 * th)
    assert torch.allclose(dq, ref, atol=1e-18)


def test_drift_moves_the_instrument_linearly_in_time():
    robot = torchcal.load_robot("ur5")
    q = _q(4)
    t = torch.tensor([0.0, 10.0, 20.0, 30.0], dtype=F64)
    rates = torch.tensor([1e-6, 0, 0, 0, 0, 0], dtype=F64)
    m = MeasurementModel(robot, [Drift("t", "instrument", rates=rates)])
    with torch.no_grad():
        p = m(Context(q=q, t=t))
        p0 = robot.probe_position(q)
    # identity instrument: a pure x translation of 1e-6 m/s * t
    assert torch.allclose(p - p0, torch.stack([t * 1e-6, 0 * t, 0 * t], -1), atol=1e-15)


def test_scale_drift_with_temperature():
    robot = torchcal.load_robot("ur5")
    q = _q(3)
    temp = torch.tensor([20.0, 21.0, 22.0], dtype=F64)
    m = MeasurementModel(robot, [Drift("temperature", "scale", rates=[2.3e-5], reference=20.0)])
    with torch.no_grad():
        p = m(Context(q=q, temperature=temp))
        p0 = robot.probe_in_base(q)
    assert torch.allclose(p, p0 * (1 + 2.3e-5 * (temp - 20.0))[:, None], atol=1e-15)


def test_correction_net_shapes_and_paper_size():
    net = CorrectionNet(dof=6, hidden=29, seed=0)
    assert net.n_weights == 293  # + 3 probe coordinates = the paper's 296-dim state
    out = net(_q(5))
    assert out.shape == (5, 3) and out.dtype == F64
    robot = torchcal.load_robot("ur5")
    with torch.no_grad():
        robot.instrument.set_matrix(tf.se3_from_vector(torch.tensor([1.0, 2, 3, 0.1, 0.2, 0.3], dtype=F64)))
        m = MeasurementModel(robot, [LearnedEffect(net)])
        q = _q(5)
        p = m(Context(q=q))
        # added in the base frame, rotated into the tracker frame (paper Eq. 20)
        expected = robot.probe_position(q) + net(q) @ robot.T_tracker_base()[:3, :3].T
    assert torch.allclose(p, expected, atol=1e-15)


def test_motion_direction_holds_sign_at_rest():
    q = torch.tensor([[0.0], [0.0], [1.0], [1.0], [0.5], [0.5], [0.7]], dtype=F64)
    assert motion_direction(q)[:, 0].tolist() == [1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0]


def test_motion_direction_of_no_samples_is_empty():
    """An empty trajectory (a refit's empty held-out part) has an empty direction, not a reduction error."""
    assert motion_direction(torch.zeros(0, 6, dtype=torch.float64)).shape == (0, 6)


def test_effect_gradients_reach_their_parameters():
    robot = torchcal.load_robot("ur10")
    effects = [
        Compliance(2, 1e-6),
        Backlash(3, 1e-4, source="torque"),
        Cyclic(5, a=[1e-5, 0], b=[0, 1e-5]),
        Drift("t", "instrument", rates=[1e-7] * 6),
        LearnedEffect(CorrectionNet(seed=1)),
    ]
    m = MeasurementModel(robot, effects)
    q = _q(32)
    m(Context(q=q, t=torch.linspace(0, 100, 32, dtype=F64))).square().sum().backward()
    for e in effects:
        for name, p in e.named_parameters():
            assert p.grad is not None and p.grad.abs().sum() > 0, (e.kind, name)
