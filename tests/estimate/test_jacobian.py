"""The analytic and the chunked Jacobians of the calibration residuals against ``torch.func.jacfwd`` of the whole
forward pass, the chain product against the 4 x 4 product it replaces, and LM results unchanged by either."""

import math
from pathlib import Path

import pytest
import torch

import torchcal
from torchcal.effects import Backlash, Compliance, Context, Cyclic, Drift, MeasurementModel
from torchcal.estimate.lm import levenberg_marquardt
from torchcal.estimate.problem import FreeParameters, jacobian_of, prior_sigmas, residual_function, whitening
from torchcal.robot import transforms as tf

F64 = torch.float64
URDFS = Path(__file__).resolve().parents[2] / "robots"
ROBOTS = ["ur5", "ur10", "panda", str(URDFS / "ur10.urdf"), str(URDFS / "panda.urdf")]


def _perturbed(spec: str, seed: int = 0) -> torchcal.RobotModel:
    robot = torchcal.load_robot(spec)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for grp in robot.groups().values():
            grp.delta.copy_(1e-3 * torch.randn(grp.delta.shape, generator=g, dtype=F64))
        robot.instrument.nominal[:3, 3] = torch.tensor([1.2, -2.0, 0.4], dtype=F64)
        robot.tool.nominal.copy_(torch.tensor([0.03, -0.01, 0.09], dtype=F64))
    return robot


def _problem(robot, n=40, seed=1, effects=(), sigma_joint=8.7e-6):
    g = torch.Generator().manual_seed(seed)
    lo, hi = robot.limits[:, 0].clamp(min=-3.0), robot.limits[:, 1].clamp(max=3.0)
    q = lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)
    model = MeasurementModel(robot, list(effects))
    ctx = Context(q=q)
    with torch.no_grad():
        p = model(ctx) + 2e-5 * torch.randn(n, 3, generator=g, dtype=F64)
    W = whitening(model, ctx, None, 15e-6, sigma_joint)
    groups = robot.groups()
    sel = {f"robot.{k}.delta": grp.mask for k, grp in groups.items()}
    labels = {f"robot.{k}.delta": grp.names for k, grp in groups.items()}
    for i, e in enumerate(model.effects):
        for name, par in e.named_parameters(recurse=False):
            sel[f"effects.{i}.{name}"] = torch.ones(par.shape, dtype=torch.bool)
    free = FreeParameters(model, sel, labels)
    return model, free, ctx, p, W


@pytest.mark.parametrize("spec", ROBOTS)
def test_analytic_jacobian_equals_jacfwd(spec):
    robot = _perturbed(spec)
    model, free, ctx, p, W = _problem(robot)
    units = {i.name: i.unit for i in robot.parameter_info() if i.group == "geometry"}
    prior = prior_sigmas(free, units, 1e-3, math.radians(0.1))
    fun = residual_function(model, free, ctx, p, W, prior)
    x = free.vector() + 1e-4 * torch.randn(len(free), generator=torch.Generator().manual_seed(2), dtype=F64)
    J = fun.jacobian(x)
    J_ref = torch.func.jacfwd(fun)(x)
    assert J.shape == J_ref.shape == (3 * ctx.q.shape[0] + int(torch.isfinite(prior).sum()), len(free))
    assert float((J - J_ref).abs().max() / J_ref.abs().max()) < 1e-12


def test_analytic_jacobian_of_a_subset_of_parameters():
    robot = _perturbed("ur10")
    model, _, ctx, p, W = _problem(robot)
    g = robot.groups()
    keep = torch.zeros_like(g["geometry"].mask)
    keep[1:4, 0] = True  # a2..a4 only, instrument rotation and tool z
    sel = {
        "robot.geometry.delta": keep,
        "robot.instrument.delta": torch.tensor([0, 0, 0, 1, 1, 1], dtype=torch.bool),
        "robot.tool.delta": torch.tensor([0, 0, 1], dtype=torch.bool),
    }
    free = FreeParameters(model, sel)
    fun = residual_function(model, free, ctx, p, W)
    x = free.vector()
    assert float((fun.jacobian(x) - torch.func.jacfwd(fun)(x)).abs().max()) < 1e-12 * float(fun.jacobian(x).abs().max())


def test_chunked_jacfwd_equals_the_whole_jacfwd_with_effects():
    robot = _perturbed("ur5")
    eff = Compliance(joint=2)
    with torch.no_grad():
        for par in eff.parameters():
            par.fill_(2e-6)
    model, free, ctx, p, W = _problem(robot, n=37, effects=[eff])
    fun = residual_function(model, free, ctx, p, W, chunk=8, linear=False)  # 37 poses: 4 full chunks and a short one
    assert any(name.startswith("effects.") for name in (e.name for e in free.entries))
    x = free.vector()
    J = fun.jacobian(x)
    J_ref = torch.func.jacfwd(fun)(x)
    assert float((J - J_ref).abs().max()) <= 1e-12 * float(J_ref.abs().max())
    assert jacobian_of(fun) is fun.jacobian
    assert jacobian_of(lambda v: v) is not None  # a plain function falls back to jacfwd


@pytest.mark.parametrize("spec", ["ur10", str(URDFS / "panda.urdf")])
def test_linearised_kinematics_jacobian_equals_jacfwd_with_every_kind_of_effect(spec):
    """Joint effects, a Cartesian scale drift and an instrument drift: the kinematics replaced by its tangent gives
    reverse-mode autograd's Jacobian of the whole model (the regressors, computed under no_grad, are constants), and
    jacfwd's wherever no regressor depends on the geometry (jacfwd ignores no_grad)."""
    robot = _perturbed(spec)
    g = torch.Generator().manual_seed(6)
    effects = [
        Compliance(joint=2, k=2e-6),
        Backlash(joint=3, b=1e-4),
        Cyclic(2, harmonics=(1, 2), a=1e-4 * torch.randn(2, generator=g, dtype=F64), b=torch.zeros(2, dtype=F64)),
        Drift("temperature", "scale", rates=torch.tensor([3e-5], dtype=F64), reference=20.0),
        Drift("t", "instrument", rates=1e-6 * torch.randn(6, generator=g, dtype=F64)),
    ]
    n = 33
    lo, hi = robot.limits[:, 0].clamp(min=-3.0), robot.limits[:, 1].clamp(max=3.0)
    q = lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)
    ctx = Context(q=q, t=torch.linspace(0, 3600, n, dtype=F64), temperature=20 + torch.rand(n, generator=g, dtype=F64))
    model = MeasurementModel(robot, effects)
    with torch.no_grad():
        p = model(ctx) + 2e-5 * torch.randn(n, 3, generator=g, dtype=F64)
    W = whitening(model, ctx, None, 15e-6, 8.7e-6)
    sel = {f"robot.{k}.delta": grp.mask for k, grp in robot.groups().items()}
    for i, e in enumerate(model.effects):
        for name, par in e.named_parameters(recurse=False):
            sel[f"effects.{i}.{name}"] = torch.ones(par.shape, dtype=torch.bool)
    free = FreeParameters(model, sel)
    fun = residual_function(model, free, ctx, p, W)
    x = free.vector() + 1e-5 * torch.randn(len(free), generator=g, dtype=F64)
    J = fun.jacobian(x)
    J_ref = torch.autograd.functional.jacobian(fun, x)
    assert J.shape == J_ref.shape == (3 * n, len(free))
    assert float((J - J_ref).abs().max()) <= 1e-12 * float(J_ref.abs().max())
    # every column carries information (the test would pass trivially on zero columns)
    assert bool((J_ref.norm(dim=0) > 0).all())
    # jacfwd differs only by the compliance's torque derivative (k dtau/dd) in the geometry and lever-arm columns
    J_fwd = torch.func.jacfwd(fun)(x)
    geo = torch.tensor([e.name in ("robot.geometry.delta", "robot.tool.delta") for e in free.entries for _ in e.index])
    assert float((J - J_fwd)[:, ~geo].abs().max()) <= 1e-12 * float(J_ref.abs().max())
    assert 0 < float((J - J_fwd)[:, geo].abs().max()) < 1e-4 * float(J_ref.abs().max())


def test_instrument_columns_with_an_effect_that_reads_the_instrument_pose():
    """The instrument pose's columns are computed in closed form (dT/dd applied to the point it transforms) unless an
    effect reads the pose itself: a finite region gate maps its fallback's tracker-frame prediction into the base
    frame through it. Both ways the Jacobian equals reverse-mode autograd's of the whole model."""
    import copy

    from torchcal.effects import CorrectionNet, LearnedEffect
    from torchcal.effects.region import RegionGate

    robot = _perturbed("ur5")
    g = torch.Generator().manual_seed(8)
    n = 30
    lo, hi = robot.limits[:, 0].clamp(min=-3.0), robot.limits[:, 1].clamp(max=3.0)
    q = lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)
    torch.manual_seed(3)
    fallback = _perturbed("ur5", seed=5)
    for length, fb in ((1.0, fallback), (math.inf, None), (1.0, None)):
        net = LearnedEffect(CorrectionNet(robot.dof, hidden=5))
        gate = RegionGate(net, q[:20], length, fallback=copy.deepcopy(fb))
        assert gate.reads_instrument == (fb is not None)
        model = MeasurementModel(robot, [gate])
        ctx = Context(q=q)
        with torch.no_grad():
            p = model(ctx) + 2e-5 * torch.randn(n, 3, generator=g, dtype=F64)
        W = whitening(model, ctx, None, 15e-6, 0.0)
        sel = {f"robot.{k}.delta": grp.mask for k, grp in robot.groups().items()}
        free = FreeParameters(model, sel)
        fun = residual_function(model, free, ctx, p, W)
        x = free.vector() + 1e-5 * torch.randn(len(free), generator=g, dtype=F64)
        J, J_ref = fun.jacobian(x), torch.autograd.functional.jacobian(fun, x)
        inst = torch.tensor([e.name == "robot.instrument.delta" for e in free.entries for _ in e.index])
        assert bool(inst.any()) and float((J_ref[:, inst]).abs().max()) > 0
        assert float((J - J_ref).abs().max()) <= 1e-10 * float(J_ref.abs().max())


def test_lm_result_is_the_same_with_the_analytic_jacobian():
    robot = _perturbed("ur10", seed=3)
    model, free, ctx, p, W = _problem(robot, n=60)
    with torch.no_grad():
        for grp in robot.groups().values():
            grp.delta.zero_()
    free_x0 = free.vector()
    units = {i.name: i.unit for i in robot.parameter_info() if i.group == "geometry"}
    # the priors make the problem well posed without an identifiability analysis
    fun = residual_function(model, free, ctx, p, W, prior_sigmas(free, units, 1e-3, math.radians(0.1)))
    a = levenberg_marquardt(fun, free_x0, max_iter=30)
    b = levenberg_marquardt(fun, free_x0, max_iter=30, jacobian=torch.func.jacfwd(fun))
    assert a.status == b.status == "converged"
    # the last iterations move by round-off only (where to stop may differ by one or two of them): the
    # solutions agree to a millionth of their standard deviations
    assert float(((a.x - b.x).abs() / b.std).max()) < 1e-6
    assert abs(a.cost_history[-1] / b.cost_history[-1] - 1) < 1e-9
    assert float((a.jacobian - b.jacobian).abs().max()) < 1e-9 * float(b.jacobian.abs().max())


def test_lm_restores_the_callers_thread_count():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        seen = []
        levenberg_marquardt(
            lambda x: x - 1.0, torch.zeros(2, dtype=F64), callback=lambda *a: seen.append(torch.get_num_threads())
        )
        assert seen and set(seen) == {1}
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def _chain_4x4(robot, q):
    """The chain as products of 4 x 4 matrices (the implementation the rotation-translation form replaced)."""
    O = robot.geometry.origins()
    T = O[0].expand(*q.shape[:-1], 4, 4)
    frames = []
    zero3 = torch.zeros(*q.shape[:-1], 3, dtype=q.dtype)
    for i in range(robot.dof):
        if i > 0:
            T = T @ O[i]
        T = T @ tf.homogeneous(tf.axis_angle(robot.geometry.axes[i], q[..., i]), zero3)
        frames.append(T)
    return torch.stack(frames, dim=-3), T @ O[-1]


@pytest.mark.parametrize("spec", ROBOTS)
def test_chain_equals_the_4x4_product(spec):
    robot = _perturbed(spec)
    q = torch.rand(2, 5, robot.dof, generator=torch.Generator().manual_seed(4), dtype=F64) * 6 - 3
    torch.set_grad_enabled(False)
    F, T = robot.joint_frames(q)
    F_ref, T_ref = _chain_4x4(robot, q)
    assert F.shape == F_ref.shape and T.shape == T_ref.shape == (2, 5, 4, 4)
    assert float((F - F_ref).abs().max()) < 1e-14
    assert float((T - T_ref).abs().max()) < 1e-14
    assert float((robot(q) - T_ref).abs().max()) < 1e-14
    p_ref = tf.transform_points(T_ref[0, 0], robot.t_flange_probe())
    assert float((robot.probe_in_base(q[0, 0]) - p_ref).abs().max()) < 1e-14
    torch.set_grad_enabled(True)


def test_batched_origins_agree_with_one_at_a_time():
    for spec in ("ur10", str(URDFS / "ur10.urdf")):
        robot = _perturbed(spec)
        d = 1e-3 * torch.randn(3, *robot.geometry.delta.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
        O = robot.geometry.origins(d)
        assert O.shape == (3, robot.dof + 1, 4, 4)
        for k in range(3):
            assert torch.equal(O[k], robot.geometry.origins(d[k]))


@pytest.mark.parametrize("with_effects", [False, True])
def test_the_prediction_jacobian_of_the_trust_columns_equals_central_differences(with_effects):
    """``covariance.model_jacobian`` (the fit's Jacobian, unwhitened), which carries the covariance to the trust
    columns' sigma, against central differences of the whole model (what it replaced): the same to 1e-7 of each
    column's largest element without effects; with a compliance, whose gravity torque the fit's Jacobian holds
    constant (the covariance is the fit's, with that Jacobian), the geometry's columns differ by its share, 2e-4."""
    from torchcal.estimate.covariance import central_jacobian, model_jacobian

    effects = (Compliance(joint=2, k=2e-6), Cyclic(joint=3, harmonics=(1,))) if with_effects else ()
    model, free, ctx, _, _ = _problem(_perturbed("ur10"), effects=effects)
    x0 = free.vector()
    J = model_jacobian(model, free, ctx, x0)
    J_ref = central_jacobian(model, free, ctx, torch.full((len(x0),), 1e-6, dtype=F64))
    assert J.shape == J_ref.shape == (len(ctx.q), 3, len(x0))
    rel = (J - J_ref).abs().amax(dim=(0, 1)) / J_ref.abs().amax(dim=(0, 1)).clamp(min=1e-300)
    assert float(rel.max()) <= (5e-4 if with_effects else 1e-7)
    if with_effects:  # the effects' own columns are exact
        own = torch.tensor([n.startswith("effects.") for n in free.names])
        assert float(rel[own].max()) <= 1e-7
    assert torch.equal(free.vector(), x0)
