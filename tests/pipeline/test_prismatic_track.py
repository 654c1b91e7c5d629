"""A UR10 on a linear track (a prismatic first joint) end to end through the command line: simulate, calibrate
(kinematic and the closed loop), predict, compensate, and the calibrated URDF reloaded."""

import csv
import json

import pytest
import torch

import torchcal
from torchcal.cli import main
from torchcal.data import read_measurements
from torchcal.sim import SimConfig, simulate

ROBOT = "ur10_track"
SIM = ["--seed", "1", "--poses", "200", "--test-poses", "100"]


def rmse(pred, test):
    p = read_measurements(pred, require_positions=True, dof=7).p
    return float((p - test.p).norm(dim=1).square().mean().sqrt())


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("track")
    assert main(["simulate", "--robot", ROBOT, "--out", str(root / "sim"), *SIM, "--quiet"]) == 0
    for method in ("kinematic", "auto"):
        out = root / method
        cmd = ["calibrate", str(root / "sim" / "train.csv"), "--robot", ROBOT, "--out", str(out), "--method", method]
        assert main([*cmd, "--quiet"]) == 0
        assert (
            main(["predict", str(out), str(root / "sim" / "test.csv"), "--out", str(root / f"{method}.csv"), "--quiet"])
            == 0
        )
    return root


@pytest.mark.slow
def test_simulated_track_campaign_biases_the_track_and_reads_it_in_metres(runs):
    truth = json.loads((runs / "sim" / "truth.json").read_text())
    names = truth["geometry"]["names"]
    delta = dict(zip(names, truth["geometry"]["delta"]))
    assert delta["d1"] != 0.0 and delta["theta1"] != 0.0  # the track's zero offset and its turn about its axis
    test = read_measurements(runs / "sim" / "test.csv", dof=7)
    assert 0.5 < float(test.q[:, 0].max() - test.q[:, 0].min()) <= 2.0  # metres along the 2 m track


def test_held_out_error_is_that_of_the_true_model_form_and_nothing_is_named(runs):
    test = read_measurements(runs / "sim" / "test.csv", dof=7)
    kinematic, auto = rmse(runs / "kinematic.csv", test), rmse(runs / "auto.csv", test)
    # the noise floor: the simulation's own true model on the same test poses
    campaign = simulate(SimConfig(robot=ROBOT, seed=1, poses=200, test_poses=100))
    with torch.no_grad():
        p_true = campaign.model(torchcal.effects.Context(q=campaign.test.q))
        floor = float((p_true - test.p).norm(dim=1).square().mean().sqrt())
    print(f"test RMSE: true model {floor * 1e3:.4f} mm, kinematic {kinematic * 1e3:.4f}, auto {auto * 1e3:.4f}")
    report = json.loads((runs / "auto" / "report.json").read_text())
    assert report["effects"] == []  # a clean campaign: geometry is all there is
    assert kinematic <= 1.2 * floor  # the kinematic fit is the true model's form here
    assert auto <= 1.2 * kinematic


def test_compensate_reaches_the_test_points_within_the_track_limits(runs):
    out = runs / "joints.csv"
    assert main(["compensate", str(runs / "auto"), str(runs / "sim" / "test.csv"), "--out", str(out), "--quiet"]) == 0
    rows = list(csv.DictReader(line for line in out.read_text().splitlines() if not line.startswith("#")))
    assert [r["status"] for r in rows] == ["converged"] * 100
    track = torch.tensor([float(r["q1"]) for r in rows], dtype=torch.float64)
    assert bool(((track >= -1.0) & (track <= 1.0)).all())  # metres


def test_calibrated_urdf_reloads_with_the_prismatic_track(runs):
    import pytorch_kinematics as pk
    import yourdfpy

    path = runs / "kinematic" / "robot_calibrated.urdf"
    assert yourdfpy.URDF.load(str(path), load_meshes=False).joint_map["track"].type == "prismatic"
    back = torchcal.load_robot(path, tip_link="flange")
    assert back.joint_types == ("prismatic",) + ("revolute",) * 6 and back.limits[0].tolist() == [-1.0, 1.0]
    report = json.loads((runs / "kinematic" / "report.json").read_text())
    assert report["urdf"]["max_mm"] < 1e-9  # the URDF's FK is the calibrated model's on the training poses
    chain = pk.build_serial_chain_from_urdf(path.read_bytes(), "flange", "base")
    q = read_measurements(runs / "sim" / "test.csv", dof=7).q
    with torch.no_grad():
        T = back(q)
    assert (chain.forward_kinematics(q.float()).get_matrix().double() - T).abs().max() < 1e-5  # pk reads float32


def test_a_scale_error_of_the_track_is_found_as_its_transmission():
    from torchcal.effects import Context, Transmission
    from torchcal.pipeline import Options

    c = simulate(SimConfig(robot=ROBOT, seed=3, poses=300, test_poses=100))
    c.model.add(Transmission(1, degree=1, c=[2e-4]))  # the track reads 0.2 mm short per metre of travel
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        noise = torch.randn(c.train.n, 3, generator=g, dtype=torch.float64) * 15e-6
        train = c.train.with_positions(c.model(Context(q=c.train.q)) + noise)
    run = torchcal.calibrate(ROBOT, train, Options())
    assert [(e["kind"], e["joint"]) for e in run.effects_report] == [("transmission", 1)]
    c1 = run.effects_report[0]["params"]["c"]
    assert abs(c1["value"] - 2e-4) < 4 * c1["std"]
    assert run.stages[-1].rmse < 0.5 * run.stages[1].rmse  # held out: the geometry alone cannot absorb a scale
