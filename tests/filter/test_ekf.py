"""The integrated ANN-EKF: linear toy = batch least squares, Jacobians, relative kinematics, re-iteration,
divergence, equivalent paths."""

import math

import pytest
import torch

import torchcal
from torchcal.effects import CorrectionNet
from torchcal.estimate import check_jacobian
from torchcal.filter import EKFConfig, EKFTrainer
from torchcal.robot import transforms as tf

F64 = torch.float64


def _setup(n=300, seed=0, noise=15e-6):
    """A short smooth joint path, a tracker pose, a true network and noisy measurements."""
    g = torch.Generator().manual_seed(seed)
    robot = torchcal.load_robot("ur5")
    with torch.no_grad():
        robot.instrument.set_matrix(tf.se3_from_vector(torch.tensor([2.0, 0.5, 0.3, 0.01, -0.02, 2.0], dtype=F64)))
        robot.tool.nominal.copy_(torch.tensor([0.0, 0.0, 0.1], dtype=F64))
    s = torch.linspace(0, 1, n, dtype=F64)[:, None]
    q = torch.tensor([0.3, -1.2, 1.4, -1.0, 1.2, 0.2], dtype=F64) + 0.8 * torch.sin(
        2 * math.pi * s * torch.tensor([1.0, 0.7, 0.5, 1.3, 0.9, 0.4], dtype=F64))
    truth = CorrectionNet(seed=seed + 1)
    with torch.no_grad():
        R = robot.T_tracker_base()[:3, :3]
        y = robot.probe_position(q) + truth(q) @ R.T + noise * torch.randn(n, 3, generator=g, dtype=F64)
    return robot, truth, q, y


def test_relative_kinematics_prediction_equals_forward_kinematics():
    robot, truth, q, _ = _setup()
    tr = EKFTrainer(robot, truth)
    with torch.no_grad():
        p = robot.probe_position(q)
    t = tr.predict_geometric(p[0], q)
    assert (t - p).abs().max() < 1e-12


def test_network_and_probe_jacobians_against_finite_differences():
    net = CorrectionNet(seed=3)
    q = torch.rand(4, 6, dtype=F64)
    w = net.flat()
    _, J = net.jacobian_flat(w, q)
    assert check_jacobian(lambda ww: net.forward_flat(ww, q), w, J) < 1e-7
    robot = torchcal.load_robot("ur10")
    with torch.no_grad():
        _, Jq = robot.probe_jacobian(q)
        for i in range(len(q)):
            assert check_jacobian(lambda qi: robot.probe_in_base(qi[None])[0], q[i], Jq[i]) < 1e-7


def test_filter_on_a_linear_toy_equals_batch_least_squares():
    # freeze the hidden layer (zero prior variance): the observation is then linear in the state
    # [W2, b2, t], no process noise -> the EKF is recursive least squares and must equal the batch solution
    robot, truth, q, y = _setup(n=150, seed=2, noise=1e-5)
    net = CorrectionNet(seed=7)
    w0 = net.flat()
    nw, H, D = net.n_weights, net.hidden, net.dof
    active = torch.zeros(nw + 3, dtype=torch.bool)
    active[H * D + H :] = True  # W2, b2 and the 3 position coordinates
    sig = torch.where(active, torch.tensor(0.3, dtype=F64), torch.tensor(0.0, dtype=F64))
    sig[-3:] = 1e-3
    cfg = EKFConfig(q_t=0.0, sigma_joint=0.0, sigma_tracker=1e-5, reiterate_every=0, adapt_qyy=False)
    tr = EKFTrainer(robot, net, cfg)
    t0 = y[0] + 2e-4
    res = tr.run(q, y, len(q), w0, t0=t0, P0=torch.diag(sig**2))
    # batch: minimise |x_a - x0_a|^2_P0 + sum |y_i - t0 - D_i - R os (W2 a_i + b2)|^2 / s^2
    with torch.no_grad():
        p = robot.probe_position(q)
        Dsp = p - p[0]
        R = robot.T_tracker_base()[:3, :3]
        a = torch.tanh(((q - net.q_offset) / net.q_scale) @ net.fc1.weight.T + net.fc1.bias)
    os = float(net.out_scale)
    rows = []
    for i in range(len(q)):
        A_w2 = os * R @ torch.kron(torch.eye(3, dtype=F64), a[i][None, :])  # d/dW2 (row-major)
        rows.append(torch.cat([A_w2, os * R, torch.eye(3, dtype=F64)], dim=1))
    A = torch.cat(rows)  # (3N, 3H + 6)
    z = (y - Dsp).reshape(-1)
    x0 = torch.cat([w0[active[:-3].nonzero().flatten()], t0])
    Pinv = torch.diag(1.0 / sig[active] ** 2)
    Nmat = Pinv + A.T @ A / 1e-10
    rhs = Pinv @ x0 + A.T @ z / 1e-10
    x_batch = torch.linalg.solve(Nmat, rhs)
    x_ekf = torch.cat([res.w[0][active[:-3].nonzero().flatten()], res.t[0] - Dsp[-1]])
    assert res.status == ["ok"]
    # what the data determine agrees to round-off; the weights themselves to the conditioning allows
    # (t0 and the output bias b2 are exactly collinear, separated only by their priors)
    assert (A @ x_ekf - A @ x_batch).abs().max() < 1e-9  # 1e-4 of the noise sigma (1e-5 m)
    assert (x_ekf - x_batch).abs().max() / x_batch.abs().max() < 1e-4


def test_reiteration_improves_a_perturbed_net():
    robot, truth, q, y = _setup(n=400, seed=4, noise=1e-5)
    tr = EKFTrainer(robot, truth, EKFConfig())
    w = truth.flat()
    g = torch.Generator().manual_seed(9)
    w_bad = w * (1 + 0.3 * torch.randn(w.shape, generator=g, dtype=F64))
    with torch.no_grad():
        corr = (y - robot.probe_position(q)) @ robot.T_tracker_base()[:3, :3]
    before = float((truth.forward_flat(w_bad, q) - corr).norm(dim=-1).square().mean().sqrt())
    w_new, info = tr._reiterate(w_bad[None], q[None], corr[None], 30)
    after = float((truth.forward_flat(w_new[0], q) - corr).norm(dim=-1).square().mean().sqrt())
    assert after < 0.3 * before
    assert info["lm_iterations"][0] <= 30


def test_divergence_is_detected_and_reported():
    robot, truth, q, y = _setup(n=400, seed=5)
    y_bad = y.clone()
    y_bad[200:] += 0.05  # the tracker was bumped by 5 cm half way: far outside any chi-square band
    res = EKFTrainer(robot, truth, EKFConfig(reiterate_every=0, adapt_qyy=False)).run(q, y_bad, len(q), truth.flat())
    assert res.diverged and "diverged" in res.status[0] and "NIS" in res.status[0]
    ok = EKFTrainer(robot, truth, EKFConfig(reiterate_every=0)).run(q, y, len(q), truth.flat())
    assert not ok.diverged
    # a consistent filter: NIS averages about 3 (its chi-square degrees of freedom)
    assert 2.0 < float(ok.nis.nanmean()) < 4.0


def test_fast_and_baseline_paths_agree_and_draws_batch():
    robot, truth, q, y = _setup(n=120, seed=6)
    w = truth.flat()
    w2 = torch.stack([w, w * 1.05])
    fast = EKFTrainer(robot, truth, EKFConfig(reiterate_every=0)).run(q, y, 100, w2)
    slow = EKFTrainer(robot, truth, EKFConfig(reiterate_every=0, jacobian="autograd")).run(q, y, 100, w2)
    assert (fast.prediction - slow.prediction).abs().max() < 1e-10
    single = EKFTrainer(robot, truth, EKFConfig(reiterate_every=0)).run(q, y, 100, w2[1])
    assert (single.prediction[0] - fast.prediction[1]).abs().max() < 1e-11  # batched kernels round differently


def test_config_validation():
    with pytest.raises(torchcal.OptionError):
        EKFConfig(jacobian="magic")
