"""Effects that carry the identified forms (Cyclic of any orders, exponential Drift, Transmission) and the
form selection of torchcal.diagnose.forms on residuals made from known formulas (no calibration needed)."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.diagnose.forms import identify_form
from torchcal.diagnose.localise import candidate_variables, workspace
from torchcal.effects import Context, Cyclic, Drift, MeasurementModel, Transmission, effect_from_config
from torchcal.errors import OptionError
from torchcal.robot import load_robot
from torchcal.sim.poses import Scene, random_poses

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _roundtrip(eff):
    cfg = {"class": type(eff).__name__, **eff.config()}
    new = effect_from_config(cfg)
    new.load_state_dict(eff.state_dict())
    return new


# ------------------------------------------------------------------------------------------------ effects
def test_cyclic_any_orders_and_default_unchanged():
    q = torch.linspace(-3, 3, 50, dtype=F64)[:, None].repeat(1, 6)
    ctx = Context(q=q)
    eff = Cyclic(3, harmonics=[3, 7], a=[1e-4, 2e-5], b=[-3e-5, 4e-5])
    want = (
        1e-4 * torch.sin(3 * q[:, 2])
        + 2e-5 * torch.sin(7 * q[:, 2])
        - 3e-5 * torch.cos(3 * q[:, 2])
        + 4e-5 * torch.cos(7 * q[:, 2])
    )
    dq = eff(None, ctx)
    assert torch.allclose(dq[:, 2], want) and bool((dq[:, [0, 1, 3, 4, 5]] == 0).all())
    assert Cyclic(2).config() == {"joint": 2, "harmonics": [1, 2]}
    back = _roundtrip(eff)
    assert back.config()["harmonics"] == [3, 7] and torch.allclose(back(None, ctx), dq)
    for bad in ([], [0], [2, 2]):
        with pytest.raises(OptionError):
            Cyclic(1, harmonics=bad)


def test_drift_exponential_form():
    t = torch.linspace(0, 3600, 100, dtype=F64)
    ctx = Context(q=torch.zeros(100, 6, dtype=F64), t=t)
    rates = torch.tensor([1e-7, -2e-7, 3e-7, 0, 0, 0], dtype=F64)
    eff = Drift("t", "instrument", rates=rates, form="exponential", tau=600.0)
    xi = eff(None, ctx)
    g = 600.0 * (1 - torch.exp(-t / 600.0))
    assert torch.allclose(xi, g[:, None] * rates)
    assert eff.tau == pytest.approx(600.0)
    eff.scale_(2.0)  # the size doubles, the shape stays
    assert eff.tau == pytest.approx(600.0) and torch.allclose(eff.rates, 2 * rates)
    back = _roundtrip(eff)
    assert back.form == "exponential" and torch.allclose(back(None, ctx), eff(None, ctx))
    assert "log_tau" in dict(eff.named_parameters())  # fitted jointly by the solver
    lin = Drift("t", "instrument", rates=rates)
    assert lin.config() == {"variable": "t", "target": "instrument"}  # older configs unchanged
    long = Drift("t", "instrument", rates=rates, form="exponential", tau=1e9)
    assert torch.allclose(long(None, ctx), lin(None, ctx), rtol=1e-5)
    with pytest.raises(OptionError):
        Drift("t", form="quadratic")
    with pytest.raises(OptionError):
        Drift("t", form="exponential", tau=0.0)


def test_transmission_polynomial():
    q = torch.linspace(-2, 2, 30, dtype=F64)[:, None].repeat(1, 6)
    ctx = Context(q=q)
    eff = Transmission(4, degree=2, c=[2e-4, -5e-5])
    assert eff.kind == "transmission"
    assert torch.allclose(eff(None, ctx)[:, 3], 2e-4 * q[:, 3] - 5e-5 * q[:, 3] ** 2)
    back = _roundtrip(eff)
    assert back.degree == 2 and torch.allclose(back(None, ctx), eff(None, ctx))
    with pytest.raises(OptionError):
        Transmission(1, degree=0)


# ----------------------------------------------------------------------------- forms on formula residuals
@pytest.fixture(scope="module")
def scene():
    """A UR5 with a tracker 2.5 m away, 800 visible poses, t every 6 s; residual noise 15 um."""
    g = torch.Generator().manual_seed(11)
    robot = load_robot("ur5")
    T = torch.eye(4, dtype=F64)
    T[:3, 3] = torch.tensor([-2.5, 0.3, 0.2], dtype=F64)
    with torch.no_grad():
        robot.instrument.set_matrix(T)
        robot.tool.nominal.copy_(torch.tensor([0.03, -0.02, 0.1], dtype=F64))  # off-axis: joint 6 moves the probe
    tracker_in_base = torch.tensor([2.5, -0.3, -0.2], dtype=F64)
    q = random_poses(Scene(robot, tracker_in_base, robot.t_flange_probe().detach()), 800, g)
    t = torch.arange(800, dtype=F64) * 6.0
    model = MeasurementModel(robot)
    ctx = Context(q=q, t=t)
    noise = torch.randn(800, 3, generator=g, dtype=F64) * 15e-6
    return model, ctx, noise


def _joint_residual(model, ctx, j, dq_j):
    with torch.no_grad():
        dq = torch.zeros_like(ctx.q)
        dq[:, j - 1] = dq_j
        return model(Context(q=ctx.q + dq, t=ctx.t)) - model(ctx)


def _choose(model, ctx, r, name):
    var = next(v for v in candidate_variables(model, ctx) if v.name == name)
    return identify_form(workspace(model, ctx, r, sigma=15e-6), var)


@pytest.mark.parametrize("joint,order", [(6, 3), (1, 4), (4, 5), (5, 8)])
def test_fourier_order_selected(scene, joint, order):
    model, ctx, noise = scene
    a, b = 1.5e-4, -1e-4
    qj = ctx.q[:, joint - 1]
    r = _joint_residual(model, ctx, joint, a * torch.sin(order * qj) + b * torch.cos(order * qj)) + noise
    fc = _choose(model, ctx, r, f"q{joint}")
    assert fc.kind == "cyclic" and fc.order == [order]
    p = fc.params()
    for key, true in ((f"a{order}", a), (f"b{order}", b)):
        assert abs(p[key]["value"] - true) < 3 * p[key]["sigma"] + 0.03 * abs(true)
    forms = {row["form"] for row in fc.to_dict()["bic_table"]}
    assert {"none", "fourier", "fourier_first", "polynomial"} <= forms
    eff = fc.effect(model)
    assert isinstance(eff, Cyclic) and eff.joint == joint


def test_polynomial_is_transmission(scene):
    model, ctx, noise = scene
    r = _joint_residual(model, ctx, 3, 2e-4 * ctx.q[:, 2]) + noise
    fc = _choose(model, ctx, r, "q3")
    assert fc.kind == "transmission" and fc.order == 1
    assert abs(fc.params()["c1"]["value"] - 2e-4) < 3 * fc.params()["c1"]["sigma"] + 4e-6
    assert isinstance(fc.effect(model), Transmission)


@pytest.mark.parametrize("tau,axis", [(300.0, (1.0, 0.0, 0.0)), (3600.0, (0.0, 0.0, 1.0))])
def test_exponential_time_constant(scene, tau, axis):
    model, ctx, noise = scene
    u = torch.tensor(axis, dtype=F64)
    r = 8e-5 * (1 - torch.exp(-ctx.t / tau))[:, None] * u + noise
    fc = _choose(model, ctx, r, "t")
    assert fc.kind == "drift" and fc.form == "exponential"
    assert abs(fc.best.tau - tau) < 2 * fc.best.tau_sigma
    assert fc.to_dict()["params"]["tau"]["sigma"] > 0
    eff = fc.effect(model)
    assert isinstance(eff, Drift) and eff.form == "exponential" and eff.tau == pytest.approx(fc.best.tau)
    # the module reproduces the fitted drift (up to the instrument translation the projection removed)
    with torch.no_grad():
        dp = MeasurementModel(model.robot, [eff])(ctx) - model(ctx)
    fitted = fc.best.beta[None, :] * (-torch.expm1(-(ctx.t - fc.reference) / fc.best.tau))[:, None]
    assert torch.allclose(dp, fitted, atol=1e-9)


def test_linear_drift_and_compliance_and_step(scene):
    model, ctx, noise = scene
    r = 2e-8 * (ctx.t - ctx.t[0])[:, None] * torch.tensor([0.0, 1.0, 0.0], dtype=F64) + noise
    fc = _choose(model, ctx, r, "t")
    assert fc.kind == "drift" and fc.form == "linear"
    tau2 = model.robot.gravity_torques(ctx.q)[:, 1].detach()
    fc = _choose(model, ctx, _joint_residual(model, ctx, 2, 2e-6 * tau2) + noise, "tau2")
    assert fc.kind == "compliance" and fc.effect(model).k.item() == pytest.approx(2e-6, rel=0.1)
    s = torch.sign(tau2)
    fc = _choose(model, ctx, _joint_residual(model, ctx, 2, 5e-5 * s) + noise, "flank2")
    assert fc.kind == "backlash" and fc.effect(model).b.item() == pytest.approx(1e-4, rel=0.1)


def test_noise_alone_selects_none(scene):
    model, ctx, noise = scene
    for name in ("q2", "t"):
        assert _choose(model, ctx, noise, name).form == "none"
    assert math.isfinite(_choose(model, ctx, noise, "q2").best.bic)
