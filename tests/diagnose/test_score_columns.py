"""The score tests' candidate columns through the linearised kinematics equal jacfwd through the whole model."""

import math

import torch

from torchcal.diagnose import candidates
from torchcal.diagnose.score import candidate_columns
from torchcal.effects import Context, Cyclic, MeasurementModel
from torchcal.estimate.fit import place_instrument_and_tool
from torchcal.estimate.problem import linear_kinematics, whitening
from torchcal.sim import SimConfig, simulate


def test_candidate_columns_with_the_linearised_kinematics_equal_the_full_jacfwd():
    c = simulate(SimConfig(robot="ur5", poses=80, test_poses=0, seed=2))
    robot = c.model.robot
    place_instrument_and_tool(robot, c.train.q, c.train.p)
    g = torch.Generator().manual_seed(0)
    model = MeasurementModel(robot, [Cyclic(3, a=1e-4 * torch.randn(2, generator=g, dtype=torch.float64))])
    ctx = Context.from_measurements(c.train, trajectory=False)
    W = whitening(model, ctx, None, 15e-6, math.radians(0.0005))
    cands, _ = candidates(robot, ctx)
    kinds = {x.kind for x in cands}
    assert {"compliance", "backlash", "cyclic", "drift"} <= kinds  # joint, Cartesian and instrument forms
    fk = linear_kinematics(model, ctx)
    for cand in cands:
        ref = candidate_columns(model, cand, ctx, c.train.p, W)
        got = candidate_columns(model, cand, ctx, c.train.p, W, fk)
        assert got.shape == ref.shape == (3 * c.train.n, cand.n_params)
        assert float(ref.abs().max()) > 0
        assert float((got - ref).abs().max()) <= 1e-12 * float(ref.abs().max()), cand.name


def test_no_backlash_candidate_from_a_gravity_torque_of_round_off_size():
    # the UR5's wrist link 6 has its centre of mass on the joint-6 axis: the torque there is ~1e-16 N m, its sign noise
    c = simulate(SimConfig(robot="ur5", poses=200, test_poses=0, seed=7))
    robot = c.model.robot
    ctx = Context.from_measurements(c.train, trajectory=False)
    tau = robot.gravity_torques(ctx.q).detach()
    assert float(tau[:, 5].abs().max()) < 1e-12 < float(tau[:, 4].abs().max())
    cands, skipped = candidates(robot, ctx)
    names = {x.name for x in cands}
    assert "backlash:6" not in names and "backlash:5" in names
    assert "round-off" in {s["name"]: s["reason"] for s in skipped}["backlash:6"]
