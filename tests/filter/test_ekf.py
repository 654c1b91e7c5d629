"""The integrated ANN-EKF: linear toy = batch least squares, Jacobians, relative kinematics, re-iteration,
divergence, equivalent paths, any nn.Module, the start check, the docstring example."""

import doctest
import math

import pytest
import torch

import torchcal
import torchcal.filter.ekf as ekf_module
from torchcal._threads import torch_threads
from torchcal.effects import CorrectionNet
from torchcal.estimate import check_jacobian
from torchcal.filter import EKFConfig, EKFTrainer, FlatModule
from torchcal.filter._kalman import ModuleJacobian, NetworkJacobian
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
        2 * math.pi * s * torch.tensor([1.0, 0.7, 0.5, 1.3, 0.9, 0.4], dtype=F64)
    )
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


# ------------------------------------------------------------------------------ any nn.Module
def _user_net(seed=0, width=32):
    """A user's network: 2 hidden layers of ``width``, SiLU, output scaled to sub-millimetre corrections."""
    torch.manual_seed(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(6, width, dtype=F64),
        torch.nn.SiLU(),
        torch.nn.Linear(width, width, dtype=F64),
        torch.nn.SiLU(),
        torch.nn.Linear(width, 3, dtype=F64),
    )
    with torch.no_grad():
        net[4].weight.mul_(1e-3)
        net[4].bias.zero_()
    return net


def test_module_path_equals_hand_derived_jacobian_on_correction_net():
    robot, truth, q, y = _setup(n=150, seed=8)
    w = torch.stack([truth.flat(), truth.flat() * 1.03])
    # the step Jacobians themselves, at a few samples and both draws
    R = robot.T_tracker_base()[:3, :3].detach()
    qD = q.expand(2, *q.shape)
    hand, func = NetworkJacobian(truth, qD, R, 2), ModuleJacobian(truth, qD, R, 2)
    for i in (0, 37, 149):
        ng_h, H_h = hand(w, i)
        ng_f, H_f = func(w, i)
        assert (ng_h - ng_f).abs().max() < 1e-18
        assert (H_h - H_f).abs().max() < 1e-15 * H_h.abs().max()
    # and whole passes
    a = EKFTrainer(robot, truth, EKFConfig(reiterate_every=0, jacobian="analytic")).run(q, y, 120, w)
    b = EKFTrainer(robot, truth, EKFConfig(reiterate_every=0, jacobian="module")).run(q, y, 120, w)
    assert a.status == b.status == ["ok", "ok"]
    assert (a.prediction - b.prediction).abs().max() < 1e-12
    assert (a.P - b.P).abs().max() < 1e-12 * a.P.abs().max()


def test_user_module_jacobian_against_finite_differences_and_a_pass_against_the_baseline():
    net = _user_net()
    flat = FlatModule(net, 6)
    w = flat.flat()
    q = torch.rand(5, 6, dtype=F64, generator=torch.Generator().manual_seed(1)) * 2 - 1
    g, J = flat.jacobian_flat(w, q)
    assert J.shape == (5, 3, flat.n_weights)
    assert check_jacobian(lambda ww: flat.forward_flat(ww, q), w, J) < 1e-7
    # the per-step Jacobian of the fast path, rotated, against central finite differences
    robot, truth, qt, y = _setup(n=200, seed=9)
    R = robot.T_tracker_base()[:3, :3].detach()
    step = ModuleJacobian(flat, qt[None], R, 1)
    x = torch.cat([w, torch.zeros(3, dtype=F64)])[None].clone()
    _, H = step(x[:, : flat.n_weights], 17)
    assert check_jacobian(lambda ww: flat.forward_flat(ww, qt[17:18])[0] @ R.T, w, H[0, :, : flat.n_weights]) < 1e-7
    # a short pass: the fast path with a user's module equals the slow reference (per-step jacrev, dense Joseph
    # form, O(n^3) per step: a narrower network of the same form keeps it quick)
    net = _user_net(width=8)
    w = FlatModule(net, 6).flat()
    fast = EKFTrainer(robot, net, EKFConfig(reiterate_every=0)).run(qt, y, 150, w)
    slow = EKFTrainer(robot, net, EKFConfig(reiterate_every=0, jacobian="autograd")).run(qt, y, 150, w)
    assert fast.status == slow.status == ["ok"]
    # the two Joseph forms round differently and many weight directions are unobserved, so round-off grows along
    # the pass: 1e-10 m over the first 20 updates, within 1e-8 m (1/1500 of the tracker noise) after 150
    diff = (fast.prediction - slow.prediction).abs()
    assert diff[:, :20].max() < 1e-10 and diff.max() < 1e-8
    # the user's module is untouched (the filter works on its own copies)
    assert torch.equal(torch.nn.utils.parameters_to_vector(net.parameters()).detach(), w)


def test_user_module_reiteration_and_pcm_weights():
    robot, truth, q, y = _setup(n=300, seed=10, noise=1e-5)
    net = _user_net(1, width=8)
    tr = EKFTrainer(robot, net, EKFConfig(reiterate_every=100, reiterate_iterations=(5, 5)))
    w0 = tr.pcm_weights(q[:200], y[:200], FlatModule(net, 6).flat(), iterations=10)
    res = tr.run(q, y, 250, w0)
    assert res.status == ["ok"] and len(res.reiterations) == 2
    assert torch.isfinite(res.prediction).all()


def test_analytic_jacobian_needs_a_correction_net():
    robot, *_ = _setup(n=10)
    with pytest.raises(torchcal.OptionError, match="CorrectionNet"):
        EKFTrainer(robot, _user_net(), EKFConfig(jacobian="analytic"))


# ------------------------------------------------------------------------------------- the start
def test_start_is_checked_and_can_be_fitted():
    robot, truth, q, y = _setup(n=300, seed=11)
    nominal = torchcal.load_robot("ur5")  # tracker pose and lever arm not fitted
    with pytest.raises(torchcal.EstimationError, match="tracker pose and the lever arm"):
        EKFTrainer(nominal, truth, EKFConfig(reiterate_every=0)).run(q, y, 250, truth.flat())
    fitted = EKFTrainer(nominal, truth, EKFConfig(reiterate_every=0, start="fit"))
    res = fitted.run(q, y, 250, truth.flat())
    # the rigid fit also absorbs part of the network's field: the fitted start is near, not at, the simulated one
    assert res.status == ["ok"] and res.start_misfit < 1e-3
    assert (res.robot.T_tracker_base() - robot.T_tracker_base()).abs().max() < 1e-2
    assert float((res.prediction - y)[0, :250].norm(dim=-1).square().mean().sqrt()) < 1e-4
    assert torch.equal(nominal.T_tracker_base(), torchcal.load_robot("ur5").T_tracker_base())  # robot untouched
    good = EKFTrainer(robot, truth, EKFConfig(reiterate_every=0)).run(q, y, 250, truth.flat())
    assert good.start_misfit < 1e-4


def test_docstring_example_runs():
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    tests = doctest.DocTestFinder().find(ekf_module.EKFTrainer, "EKFTrainer", module=ekf_module)
    for t in tests:
        runner.run(t)
    result = runner.summarize(verbose=False)
    assert result.attempted >= 10 and result.failed == 0


def test_pass_pins_one_thread_and_restores_the_callers():
    robot, truth, q, y = _setup(n=50, seed=12)
    seen = []

    class Spy(EKFTrainer):
        def kinematics(self, qq):
            seen.append(torch.get_num_threads())
            return super().kinematics(qq)

    before = torch.get_num_threads()
    with torch_threads(2):
        Spy(robot, truth, EKFConfig(reiterate_every=0)).run(q, y, 40, truth.flat())
        assert torch.get_num_threads() == 2
    assert seen and set(seen) == {1}
    assert torch.get_num_threads() == before
