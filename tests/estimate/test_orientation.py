"""A 6-D probe's orientation (issue 26, item 4): the file columns, the orientation model and its Jacobian, and
simulate-and-recover of the full pose: the probe frame's rotation within 3 sigma, a parameter that only orientation
makes estimable, the position's held-out error not worse than position-only, and the command line end to end."""

import json
import math
from pathlib import Path

import pytest
import torch

import torchcal
from torchcal.data import read_measurements, write_measurements
from torchcal.effects import Compliance, Context, MeasurementModel
from torchcal.errors import MeasurementFileError
from torchcal.estimate.check import check_jacobian
from torchcal.estimate.fit import errors, orientation_errors, place_tool_rotation, selection
from torchcal.estimate.problem import FreeParameters, orientation_error, orientation_function, orientation_whitening
from torchcal.pipeline import Options, calibrate
from torchcal.robot import transforms as tf
from torchcal.sim import SimConfig, simulate

F64 = torch.float64


@pytest.fixture(scope="module")
def campaign():
    # zero angle biases: the probe frame's true rotation is then what the fit can name (the angles held fixed for
    # the instrument and the tool, theta1 and theta6, have no bias to pass on to it)
    return simulate(
        SimConfig(robot="ur5", poses=240, test_poses=60, seed=4, orientation_sigma_deg=0.01, sigma_angle_deg=0.0)
    )


def test_orientation_columns_round_trip_and_errors(tmp_path, campaign):
    m = campaign.train
    path = tmp_path / "full.csv"
    write_measurements(path, m)
    back = read_measurements(path, dof=6)
    assert torch.equal(back.r, m.r) and torch.equal(back.sigma_r, m.sigma_r)
    assert back.subset([2, 0]).r.shape == (2, 3) and back.without_orientation().r is None
    text = path.read_text().splitlines()
    header = text[[i for i, line in enumerate(text) if line.startswith("q1")][0]].split(",")
    bad = tmp_path / "bad.csv"
    # two of three orientation columns: the missing one is named
    bad.write_text("\n".join(line for line in text if not line.startswith("#")).replace(",rz,", ",other,", 1))
    with pytest.raises(MeasurementFileError, match="rz"):
        read_measurements(bad, dof=6)
    # a non-positive orientation sigma: named with its row and column
    rows = [line.split(",") for line in text if not line.startswith("#")]
    rows[2][header.index("sry")] = "0"
    bad.write_text("\n".join(",".join(r) for r in rows))
    with pytest.raises(MeasurementFileError, match="sry") as info:
        read_measurements(bad, dof=6)
    assert info.value.line == 3
    # degrees in place of radians
    rows = [line.split(",") for line in text if not line.startswith("#")]
    rows[1][header.index("rx")] = "120.0"
    bad.write_text("\n".join(",".join(r) for r in rows))
    with pytest.raises(MeasurementFileError, match="radians"):
        read_measurements(bad, dof=6)


def test_orientation_jacobian_matches_central_differences():
    robot = torchcal.load_robot("ur5")
    g = torch.Generator().manual_seed(1)
    q = torch.rand(20, 6, generator=g, dtype=F64) * 2 - 1
    robot.enable_orientation(tf.so3_exp(torch.tensor([0.3, -0.2, 0.5], dtype=F64)))
    with torch.no_grad():
        for grp in robot.groups().values():
            grp.delta.copy_(1e-3 * torch.randn(grp.delta.shape, generator=g, dtype=F64))
    model = MeasurementModel(robot, [Compliance(joint=2)])
    with torch.no_grad():
        model.effects[0].k.fill_(1e-5)
    ctx = Context(q=q)
    R_meas = tf.so3_exp(torch.randn(20, 3, generator=g, dtype=F64) * 0.01) @ model.orientation(ctx).detach()
    sel, labels = selection(model, ("geometry", "instrument", "tool"), effects=True)
    free = FreeParameters(model, sel, labels)
    assert "tool.rx" in free.names and "compliance(joint 2).k" in free.names
    W = orientation_whitening(model, ctx, None, 1e-4, 1e-5)
    fun = orientation_function(model, free, ctx, R_meas, W, chunk=7)
    x = free.vector()
    # the gravity torque is a constant in derivatives, as in the position rows: 9e-6 of the Jacobian here, at a
    # compliance ten times a UR's; every other term to central differences' 1e-6
    assert check_jacobian(fun, x, fun.jacobian(x)) < 2e-5
    x0 = x.clone()
    x0[free.names.index("compliance(joint 2).k")] = 0.0  # no torque term to leave out
    assert check_jacobian(fun, x0, fun.jacobian(x0)) < 1e-6
    # the residual is the rotation vector of R_pred R_meas^T to third order
    e = orientation_error(model.orientation(ctx).detach(), R_meas)
    E = model.orientation(ctx).detach() @ R_meas.transpose(1, 2)
    torch.testing.assert_close(e, tf.so3_log(E), rtol=1e-3, atol=1e-12)  # angles ~0.02 rad: theta^2 / 6


def test_full_pose_recovers_the_tool_rotation(campaign):
    run = calibrate("ur5", campaign.train, Options(method="kinematic"))
    fit = run.fits[-1]
    assert fit.n_orientation == run.train.n and fit.global_test["passed"]
    R_true = torch.tensor(campaign.truth["orientation"]["R_flange_probe"], dtype=F64)
    # the fit's rotation (nominal from the closed-form start, then the correction) against the truth, in the
    # correction's own (probe) axes, within 3 of the fit's standard deviations
    nominal = run.model.robot.tool_rotation.nominal
    miss = tf.so3_log(nominal.T @ R_true)
    est = run.model.robot.tool_rotation.delta.detach()
    std = torch.tensor([float(fit.result.std[fit.result.names.index(f"tool.r{a}")]) for a in "xyz"], dtype=F64)
    assert bool(((est - miss).abs() < 3 * std).all()), (est - miss, std)
    # held-out orientation at the noise floor (the angle of 3 axes of 0.01 deg noise: 0.017 deg RMS)
    e = orientation_errors(run.model, campaign.test, False)
    assert math.degrees(float(e.square().mean().sqrt())) < 0.025
    # the position is no worse than the position-only calibration's on the same held-out poses
    po = calibrate("ur5", campaign.train.without_orientation(), Options(method="kinematic"))
    e_fp = float(errors(run.model, campaign.test, False).square().mean().sqrt())
    e_po = float(errors(po.model, campaign.test, False).square().mean().sqrt())
    assert e_fp < 1.05 * e_po


def _turned(m, rows, deg: float):
    """``m`` with the orientation of ``rows`` turned ``deg`` about the tracker's z axis (a slipped frame)."""
    import dataclasses

    r = m.r.clone()
    turn = tf.so3_exp(torch.tensor([0.0, 0.0, math.radians(deg)], dtype=F64))
    r[rows] = tf.so3_log(turn @ tf.so3_exp(r[rows]))
    return dataclasses.replace(m, r=r, meta=dict(m.meta))


def test_a_block_of_gross_orientations_keeps_its_positions(campaign):
    """A sixth of the rows with their orientation 14 deg off (Series A of the real UR10 has such a block): before,
    the screening rejected those rows whole; now their orientations alone are left out, every position is fitted,
    and the held-out errors are the clean campaign's."""
    rows = torch.arange(0, 240, 6)
    run = calibrate("ur5", _turned(campaign.train, rows, 14.0), Options(method="kinematic"))
    clean = calibrate("ur5", campaign.train, Options(method="kinematic"))
    sc = run.screening
    assert sc.training.n_rejected == 0 and sc.holdout.n_rejected == 0
    dropped = torch.cat(
        [run.split.keep[sc.training.orientation_dropped_index], run.split.held[sc.holdout.orientation_dropped_index]]
    )
    assert sorted(dropped.tolist()) == rows.tolist()  # exactly the turned rows
    assert len(run.train_idx) + len(run.holdout_idx) == 240
    assert run.fits[-1].n_orientation == run.train.n - len(sc.training.orientation_dropped)
    assert run.data.orientation_used is not None and int((~run.data.orientation_used).sum()) == len(rows)
    for kind in (errors, orientation_errors):
        e, e_clean = (kind(r.model, campaign.test, False).square().mean().sqrt() for r in (run, clean))
        assert float(e) < 1.05 * float(e_clean), (kind.__name__, e, e_clean)


def test_measurements_drop_orientation_carries_through_subsets(campaign):
    m = campaign.train.drop_orientation(torch.tensor([1, 3]))
    assert m.orientation_rows[:4].tolist() == [0, 2, 4, 5] and not m.all_orientations_used
    part = m.subset([3, 4, 1])
    assert part.orientation_used.tolist() == [False, True, False] and part.orientation_rows.tolist() == [1]
    assert m.without_orientation().orientation_used is None and campaign.train.all_orientations_used
    with pytest.raises(torchcal.errors.ShapeError, match="orientation_used"):
        type(m)(q=m.q, p=m.p, orientation_used=m.orientation_used)  # without r


def test_orientation_makes_theta5_estimable():
    # a probe on the flange axis (a T-Mac's frame 109 mm along z, as on the real UR10): its position does not
    # turn with theta5's zero offset in any way the instrument pose and the lever arm cannot take up; its frame does
    c = simulate(
        SimConfig(
            robot="ur5",
            poses=200,
            test_poses=10,
            seed=1,
            orientation_sigma_deg=0.01,
            lever_arm=(0, 0, 0.02),
            lever_arm_sigma=0.0,
        )
    )
    full = calibrate("ur5", c.train, Options(method="kinematic"))
    pos = calibrate("ur5", c.train.without_orientation(), Options(method="kinematic"))
    geo_full = next(f for f in full.fits if f.identifiability is not None)
    geo_pos = next(f for f in pos.fits if f.identifiability is not None)
    assert "theta5" in geo_full.orientation_only
    assert "theta5" in {d["name"] for d in geo_pos.identifiability.fixed}
    assert "theta5" not in {d["name"] for d in geo_full.identifiability.fixed}


def test_place_tool_rotation_is_exact_without_noise():
    robot = torchcal.load_robot("ur5")
    R_fp = tf.so3_exp(torch.tensor([0.1, 2.0, -0.4], dtype=F64))
    q = torch.rand(10, 6, generator=torch.Generator().manual_seed(0), dtype=F64)
    r_meas = None
    with torch.no_grad():
        truth = torchcal.load_robot("ur5")
        truth.enable_orientation(R_fp)
        R = truth.T_tracker_base()[:3, :3] @ truth.probe_rotation(q)
        from torchcal.data.ipa import matrix_to_rotvec

        r_meas = matrix_to_rotvec(R)
    assert place_tool_rotation(robot, q, r_meas) < 1e-12
    torch.testing.assert_close(robot.tool_rotation.matrix().detach(), R_fp, rtol=0, atol=1e-12)


def test_cli_full_pose_end_to_end(tmp_path):
    from torchcal.cli import main

    def run_cli(*args):
        assert main(list(args)) == 0

    sim, cal, pred = tmp_path / "sim", tmp_path / "cal", tmp_path / "pred.csv"
    run_cli(
        "simulate",
        "--robot",
        "ur5",
        "--out",
        str(sim),
        "--seed",
        "3",
        "--poses",
        "120",
        "--test-poses",
        "20",
        "--orientation",
        "0.01",
        "--quiet",
    )
    assert "srz" in (sim / "train.csv").read_text()
    run_cli(
        "calibrate", str(sim / "train.csv"), "--robot", "ur5", "--out", str(cal), "--method", "kinematic", "--quiet"
    )
    report = json.loads((cal / "report.json").read_text())
    o = report["orientation"]
    assert [s["name"] for s in o["stages"]] == ["nominal", "geometric"]
    assert o["rms_after_deg"] < o["rms_before_deg"] and o["rows_fitted"] == report["n_train"]
    assert "## Orientation" in (cal / "report.md").read_text()
    run_cli("predict", str(cal), str(sim / "test.csv"), "--out", str(pred), "--quiet")
    got = read_measurements(pred, dof=6, require_positions=True)
    test = read_measurements(sim / "test.csv", dof=6)
    angle = torch.stack([tf.so3_log(a @ b.T).norm() for a, b in zip(tf.so3_exp(got.r), tf.so3_exp(test.r))])
    assert math.degrees(float(angle.max())) < 0.1


def test_the_orientation_rows_get_the_positions_variance_factor():
    """Orientation sigmas reported ten times too small (a probe's own noise, not what the model leaves): the factor
    that scales them gives both groups the same variance factor; priors between the two blocks are not counted."""
    from torchcal.estimate.fit import orientation_scale

    g = torch.Generator().manual_seed(0)
    n = 400
    pos, prior, ori = (
        torch.randn(3 * n, generator=g),
        torch.randn(7, generator=g) * 100,
        10 * torch.randn(3 * n, generator=g),
    )
    assert orientation_scale(torch.cat([pos, prior, ori]), n) == pytest.approx(10.0, rel=0.05)
    assert orientation_scale(torch.cat([pos, prior, pos]), n) == pytest.approx(1.0)


FANUC = str(Path(__file__).resolve().parents[1] / "robot" / "data" / "fanuc_like.yaml")


@pytest.mark.parametrize("name", ["ur5", "ur10_track", FANUC], ids=["revolute", "prismatic", "readings"])
def test_orientation_joint_jacobian_equals_forward_mode(name):
    """The joint Jacobian of the probe frame's turn (the geometric one, from the joint axes) equals ``torch.func.jvp``
    of the probe rotation per reading, with a prismatic joint (no turn) and a readings map (by the readings)."""
    from torchcal.estimate.problem import orientation_joint_jacobian

    robot = torchcal.load_robot(name)
    robot.enable_orientation(tf.so3_exp(torch.tensor([0.3, -0.2, 0.5], dtype=F64)))
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        robot.geometry.delta.copy_(torch.randn(robot.geometry.delta.shape, generator=g, dtype=F64) * 1e-2)
        robot.instrument.set_matrix(
            tf.homogeneous(tf.so3_exp(torch.tensor([0.1, 0.2, -1.0], dtype=F64)), torch.ones(3, dtype=F64))
        )
    lo, hi = robot.limits[:, 0].clamp(min=-2.0), robot.limits[:, 1].clamp(max=2.0)
    q = lo + (hi - lo) * torch.rand(5, robot.dof, generator=g, dtype=F64)
    R_tb = robot.T_tracker_base()[:3, :3]
    cols = []
    for j in range(robot.dof):
        tangent = torch.zeros_like(q)
        tangent[:, j] = 1.0
        R, dR = torch.func.jvp(robot.probe_rotation, (q,), (tangent,))
        W = dR @ R.transpose(-1, -2)  # the angular velocity's cross-product matrix, base frame
        cols.append(torch.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], -1) @ R_tb.T)
    got = orientation_joint_jacobian(MeasurementModel(robot), Context(q=q))
    torch.testing.assert_close(got, torch.stack(cols, -1), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["ur5", "ur10_track"])
def test_orientation_jacobian_with_the_chain_linearised_equals_forward_mode_through_it(name):
    """Equivalent paths agree: the Jacobian with R_base_flange replaced by its tangent (linear_rotation) equals reverse
    mode through the chain, with a compliance (its torque a constant in both, as in the position rows) and a prismatic
    joint; forward mode through the chain (linear=False) differs from both only in the geometry's columns, by the
    torque's derivative."""
    robot = torchcal.load_robot(name)
    g = torch.Generator().manual_seed(2)
    lo, hi = robot.limits[:, 0].clamp(min=-2.0), robot.limits[:, 1].clamp(max=2.0)
    q = lo + (hi - lo) * torch.rand(30, robot.dof, generator=g, dtype=F64)
    robot.enable_orientation(tf.so3_exp(torch.tensor([0.3, -0.2, 0.5], dtype=F64)))
    with torch.no_grad():
        for grp in robot.groups().values():
            grp.delta.copy_(1e-3 * torch.randn(grp.delta.shape, generator=g, dtype=F64))
    model = MeasurementModel(robot, [Compliance(joint=3)])
    with torch.no_grad():
        model.effects[0].k.fill_(1e-5)
    ctx = Context(q=q)
    R_meas = tf.so3_exp(torch.randn(30, 3, generator=g, dtype=F64) * 0.01) @ model.orientation(ctx).detach()
    sel, labels = selection(model, ("geometry", "instrument", "tool"), effects=True)
    free = FreeParameters(model, sel, labels)
    W = orientation_whitening(model, ctx, None, 1e-4, 1e-5)
    x = free.vector() + 1e-4 * torch.randn(len(free), generator=g, dtype=F64)
    fun = orientation_function(model, free, ctx, R_meas, W, chunk=7)
    reverse = torch.autograd.functional.jacobian(fun, x)
    linearised = fun.jacobian(x)
    assert float(reverse.abs().amax()) > 0
    torch.testing.assert_close(linearised, reverse, rtol=1e-10, atol=1e-10 * float(reverse.abs().amax()))
    forward = orientation_function(model, free, ctx, R_meas, W, chunk=7, linear=False).jacobian(x)
    geometry = torch.tensor([not n.startswith(("instrument.", "tool.", "compliance")) for n in free.names])
    torch.testing.assert_close(forward[:, ~geometry], reverse[:, ~geometry], rtol=1e-10, atol=1e-10)
    assert not torch.allclose(forward[:, geometry], reverse[:, geometry], rtol=1e-10, atol=1e-12)  # the torque's


def test_orientation_jacobian_of_the_instrument_in_closed_form_equals_reverse_mode():
    """The instrument pose's columns in closed form (dR_pred/dd = N R_pred) with each row's own station, a drift of
    the pose and of the arm's scale beside it, and the lever arm's zero columns: the Jacobian equals reverse mode
    through the model, and the free columns include every one of them."""
    from torchcal.effects import Drift

    robot = torchcal.load_robot("ur5")
    g = torch.Generator().manual_seed(5)
    robot.enable_orientation(tf.so3_exp(torch.tensor([0.3, -0.2, 0.5], dtype=F64)))
    robot.set_stations(["east", "west"])
    with torch.no_grad():
        robot.instrument.set_matrix(
            tf.homogeneous(tf.so3_exp(torch.tensor([0.1, 0.2, -1.0], dtype=F64)), torch.ones(3, dtype=F64)), station=1
        )
        for grp in robot.groups().values():
            grp.delta.copy_(1e-3 * torch.randn(grp.delta.shape, generator=g, dtype=F64))
    lo, hi = robot.limits[:, 0].clamp(min=-2.0), robot.limits[:, 1].clamp(max=2.0)
    q = lo + (hi - lo) * torch.rand(30, robot.dof, generator=g, dtype=F64)
    drifts = [
        Drift("temperature", "instrument", rates=[1e-5, -2e-5, 3e-5, 1e-6, -2e-6, 3e-6]),
        Drift("t", "scale", rates=[1e-7]),
    ]
    model = MeasurementModel(robot, [Compliance(joint=3), *drifts])
    with torch.no_grad():
        model.effects[0].k.fill_(1e-5)
    ctx = Context(
        q=q,
        station=torch.arange(30) % 2,
        t=torch.linspace(0.0, 3600.0, 30, dtype=F64),
        temperature=torch.linspace(20.0, 23.0, 30, dtype=F64),
    )
    R_meas = tf.so3_exp(torch.randn(30, 3, generator=g, dtype=F64) * 0.01) @ model.orientation(ctx).detach()
    sel, labels = selection(model, ("geometry", "instrument", "tool", "tool_rotation"), effects=True)
    free = FreeParameters(model, sel, labels)
    assert any(n.startswith("instrument[west]") for n in free.names) and "tool.x" in free.names
    W = orientation_whitening(model, ctx, None, 1e-4, 1e-5)
    x = free.vector() + 1e-4 * torch.randn(len(free), generator=g, dtype=F64)
    fun = orientation_function(model, free, ctx, R_meas, W, chunk=7)
    reverse = torch.autograd.functional.jacobian(fun, x)
    got = fun.jacobian(x)
    instrument = torch.tensor([n.startswith("instrument") for n in free.names])
    assert float(reverse[:, instrument].abs().amax()) > 0
    torch.testing.assert_close(got, reverse, rtol=1e-10, atol=1e-10 * float(reverse.abs().amax()))
