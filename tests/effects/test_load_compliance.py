"""Compliance driven by the row's load (issue 45): the payload's torque per row, the measured-torque form, the lumped
form's payload term, their physical bound, the simulator's loads with their truth, and predict's flags for rows
beyond the training load."""

import dataclasses

import pytest
import torch

import torchcal
from torchcal.effects import Compliance, Context, LumpedCompliance, MeasurementModel, TorqueCompliance
from torchcal.effects.joint import MAX_COMPLIANCE, joint_function_check
from torchcal.effects.registry import effect_from_config
from torchcal.errors import OptionError
from torchcal.robot.model import GRAVITY
from torchcal.sim import SimConfig, simulate
from torchcal.use.conditions import load_conditions, training_load

F64 = torch.float64


def poses(robot, n=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    lo, hi = robot.limits[:, 0].clamp(min=-3.0), robot.limits[:, 1].clamp(max=3.0)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)


@pytest.mark.parametrize("name", ["ur10", "arm7_dh"])
def test_payload_torque_is_the_jacobian_transpose_of_its_weight(name):
    """Two paths agree: the payload's torque from the chain's levers and ``J^T f`` with ``f`` its weight at the
    probe (the geometric Jacobian); no link masses needed (arm7_dh has none)."""
    robot = torchcal.load_robot(name)
    q = poses(robot)
    m = torch.linspace(0.0, 10.0, len(q), dtype=F64)
    _, J = robot.probe_jacobian(q)
    f = torch.zeros(len(q), 3, dtype=F64)
    f[:, 2] = -GRAVITY * m
    expect = (J.transpose(1, 2) @ f[:, :, None])[..., 0]
    with torch.no_grad():
        got = robot.payload_torques(q, m)
    assert torch.allclose(got, expect, atol=1e-10, rtol=0)


def test_gravity_torques_take_a_payload_per_row_and_a_centre_of_mass():
    robot = torchcal.load_robot("ur10")
    q = poses(robot)
    m = torch.tensor([0.0, 1.0, 2.0, 5.0, 5.0, 10.0, 0.5], dtype=F64)
    with torch.no_grad():
        rows = robot.gravity_torques(q, m)
        each = torch.stack([robot.gravity_torques(q[i : i + 1], float(m[i]))[0] for i in range(len(q))])
        at_probe = robot.gravity_torques(q, m, robot.t_flange_probe().expand(len(q), 3))
        static = robot.static_torques(q, m)
    assert torch.allclose(rows, each, atol=1e-10, rtol=0)
    assert torch.allclose(at_probe, rows, atol=1e-10, rtol=0) and torch.equal(static, rows)


def test_compliance_reads_the_rows_payload():
    robot = torchcal.load_robot("ur10")
    q = poses(robot)
    payload = torch.full((len(q),), 5.0, dtype=F64)
    eff = Compliance(2, k=1e-6)
    with torch.no_grad():
        loaded = eff.regressor(robot, Context(q=q, payload=payload))
        expect = robot.gravity_torques(q, 5.0)[:, 1]
        unloaded = eff.regressor(robot, Context(q=q))
    assert torch.allclose(loaded, expect, atol=1e-10, rtol=0)
    assert torch.allclose(unloaded, robot.gravity_torques(q)[:, 1].detach(), atol=1e-10, rtol=0)


def test_torque_compliance_twists_against_the_drive_torque_and_needs_torques():
    robot = torchcal.load_robot("arm7_dh")
    q = poses(robot)
    tau = torch.randn(len(q), robot.dof, dtype=F64, generator=torch.Generator().manual_seed(1)) * 10
    eff = TorqueCompliance(2, k=3e-6)
    dq = eff(robot, Context(q=q, tau=tau))
    assert torch.allclose(dq[:, 1], -3e-6 * tau[:, 1], atol=1e-18, rtol=0) and bool((dq[:, [0, 2, 3]] == 0).all())
    with pytest.raises(OptionError, match="tau1..tauN"):
        eff(robot, Context(q=q))
    again = effect_from_config({"class": "TorqueCompliance", **eff.config()})
    assert isinstance(again, TorqueCompliance) and again.joint == 2


def test_lumped_form_adds_the_payloads_torque_and_rebuilds():
    robot = torchcal.load_robot("arm7_dh")
    q = poses(robot)
    basis = torch.eye(4 * robot.dof, dtype=F64)[:, :3]
    eff = LumpedCompliance(2, basis, mode=[1e-4, 0.0, 0.0], load=True, k=2e-6)
    payload = torch.full((len(q),), 4.0, dtype=F64)
    with torch.no_grad():
        bare = eff(robot, Context(q=q))[:, 1]
        loaded = eff(robot, Context(q=q, payload=payload))[:, 1]
        expect = 2e-6 * robot.payload_torques(q, payload)[:, 1]
    assert torch.allclose(loaded - bare, expect, atol=1e-15, rtol=0)
    again = effect_from_config({"class": "LumpedCompliance", **eff.config()})
    assert again.load and again.k is not None


@pytest.mark.parametrize("k", [-1e-7, 2 * MAX_COMPLIANCE])
def test_a_load_compliance_outside_its_physical_range_is_refused(k):
    robot = torchcal.load_robot("arm7_dh")
    why = joint_function_check(TorqueCompliance(2, k=k), poses(robot), robot)
    assert why is not None and "not physical" in why
    assert joint_function_check(TorqueCompliance(2, k=1e-6), poses(robot), robot) is None


def test_simulated_loads_carry_their_truth():
    cfg = dict(robot="arm7_dh", poses=12, test_poses=6, seed=3, effects=[], torques=True, sigma_torque=0.0)
    c = simulate(SimConfig(**cfg, test_payload=10.0))
    assert c.train.payload.tolist() == [0.0] * 12 and c.test.payload.tolist() == [10.0] * 6
    assert c.truth["load"]["payload_test_kg"] == [10.0] and c.truth["load"]["masses"]["masses_kg"]
    # noise-free torques are the truth robot's drive torques at the true joints (it was given seeded masses)
    truth_robot = c.model.robot
    with torch.no_grad():
        tau = -truth_robot.gravity_torques(c.q_true[12:18], torch.full((6,), 10.0, dtype=F64))
    assert torch.allclose(c.test.tau, tau, atol=1e-9, rtol=0)
    levels = simulate(SimConfig(**cfg, payload_levels=(0.0, 5.0)))
    assert levels.train.payload[:4].tolist() == [0.0, 5.0, 0.0, 5.0]
    plain = simulate(SimConfig(robot="arm7_dh", poses=12, test_poses=6, seed=3))
    assert plain.train.payload is None and torch.equal(plain.train.q, c.train.q)  # loads draw no poses
    with pytest.raises(OptionError, match="mass in kg"):
        SimConfig(robot="ur10", payload=-1.0)


def test_rows_beyond_the_training_load_are_flagged_with_a_larger_sigma():
    robot = torchcal.load_robot("ur10")
    q = poses(robot, n=4)
    train = torchcal.data.Measurements(q=q, extra={"payload": torch.zeros(4, dtype=F64)})
    meta = {"load": training_load(train)}
    assert meta["load"]["payload_kg"] == [0.0, 0.0] and meta["load"]["payload_column"]
    rows = dataclasses.replace(train, extra={"payload": torch.tensor([0.0, 5.0, 10.0, 0.0], dtype=F64)})
    lc = load_conditions(MeasurementModel(robot, []), meta, rows, "rows.csv")
    assert lc.beyond.tolist() == [False, True, True, False]
    assert bool((lc.extrapolation[[1, 2]] > 0).all()) and bool((lc.extrapolation[[0, 3]] == 0).all())
    assert bool((lc.sigma[2] > lc.sigma[1]).all()) and bool((lc.sigma[1] > 0).all())  # grows with the distance
    assert "2 of 4 rows carry a load the run was not fitted at" in lc.note
    fitted = load_conditions(MeasurementModel(robot, [Compliance(j, k=1e-6) for j in (2, 3, 5)]), meta, rows, "r")
    assert bool((fitted.sigma[2] < lc.sigma[2]).all())  # joints whose compliance the model carries add nothing


def test_compensation_carries_the_programs_payload():
    """Commands solved with the program's payload put the loaded probe on the target; those solved at 0 kg miss
    by the load's sag."""
    from torchcal.use.compensate import compensate

    robot = torchcal.load_robot("ur10")
    model = MeasurementModel(robot, [Compliance(2, k=2e-6), Compliance(3, k=3e-6)])
    q = poses(robot, n=5, seed=4)
    payload = torch.full((5,), 10.0, dtype=F64)
    with torch.no_grad():
        targets = model(Context(q=q, payload=payload))
    loaded = compensate(model, targets, q + 0.02, context={"payload": payload})  # from a seed off the answer
    bare = compensate(model, targets, q + 0.02)
    with torch.no_grad():
        hit = (model(Context(q=loaded.q, payload=payload)) - targets).norm(dim=1)
        sag = (model(Context(q=bare.q, payload=payload)) - targets).norm(dim=1)
    assert float(hit.max()) < 1e-9 and float(sag.max()) > 1e-4
