"""Several instrument stations and probes in one campaign (issue 26): the file columns, the exact Jacobians, and
the command line end to end against the true model."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from torchcal.data import Measurements, read_measurements, write_measurements
from torchcal.effects import Context, Cyclic, MeasurementModel
from torchcal.errors import MeasurementFileError
from torchcal.estimate.fit import selection
from torchcal.estimate.problem import FreeParameters, residual_function
from torchcal.robot import load_robot

F64 = torch.float64


def _rows(n: int = 12) -> Measurements:
    g = torch.Generator().manual_seed(0)
    q = torch.rand(n, 6, generator=g, dtype=F64) - 0.5
    p = torch.rand(n, 3, generator=g, dtype=F64) + 1.0
    return Measurements(
        q=q,
        p=p,
        station=torch.tensor([0, 1, 2] * (n // 3)),
        station_names=("A", "B/C", "7"),
        probe=torch.tensor([0, 1] * (n // 2)),
        probe_names=("nest_1", "nest_2"),
    )


def test_labels_round_trip(tmp_path):
    m = _rows()
    write_measurements(tmp_path / "m.csv", m)
    back = read_measurements(tmp_path / "m.csv")
    assert back.station_names == ("A", "B/C", "7") and back.probe_names == ("nest_1", "nest_2")
    assert torch.equal(back.station, m.station) and torch.equal(back.probe, m.probe)
    assert torch.equal(back.q, m.q) and torch.equal(back.p, m.p)
    sub = back.subset([1, 2])
    assert sub.station.tolist() == [1, 2] and sub.station_names == back.station_names


def test_empty_label_names_file_line_column(tmp_path):
    f = tmp_path / "m.csv"
    f.write_text("q1,q2,q3,q4,q5,q6,x,y,z,station\n0,0,0,0,0,0,1,1,1,A\n0,0,0,0,0,0,1,1,1,\n", encoding="utf-8")
    with pytest.raises(MeasurementFileError) as err:
        read_measurements(f)
    text = str(err.value)
    assert "m.csv" in text and "3" in text and "station" in text and "empty" in text


def _model(effects=()):
    robot = load_robot("ur5")
    robot.set_stations(["A", "B", "C"])
    robot.set_probes(["1", "2"])
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for grp in (robot.geometry, robot.instrument, robot.tool):
            grp.delta.copy_(torch.randn(grp.delta.shape, generator=g, dtype=F64) * 1e-3 * grp.mask)
        robot.instrument.nominal[:, :3, 3] += torch.randn(3, 3, generator=g, dtype=F64)
        robot.tool.nominal += torch.randn(2, 3, generator=g, dtype=F64) * 0.05
    return MeasurementModel(robot, effects)


# a cyclic joint error reads no geometry (a compliance's torque does, which the linearised path holds constant)
CYCLIC = Cyclic(2, harmonics=(1, 2), a=torch.tensor([1e-4, -2e-4], dtype=F64), b=torch.tensor([3e-5, 1e-4], dtype=F64))


@pytest.mark.parametrize("effects", [(), (CYCLIC,)], ids=["analytic", "linearised"])
def test_jacobian_per_station_and_probe_equals_jacfwd(effects):
    model = _model(effects)
    m = _rows(24)
    ctx = Context(q=m.q, station=m.station, probe=m.probe)
    sel, labels = selection(model, ("geometry", "instrument", "tool"), effects=bool(effects))
    free = FreeParameters(model, sel, labels)
    W = torch.eye(3, dtype=F64).expand(m.n, 3, 3)
    x = free.vector()
    fast = residual_function(model, free, ctx, m.p, W).jacobian(x)
    slow = residual_function(model, free, ctx, m.p, W, linear=False)
    slow.jacobian = None  # the analytic path off: jacfwd of the whole model
    ref = torch.func.jacfwd(slow)(x)
    assert fast.shape == ref.shape
    assert torch.allclose(fast, ref, atol=1e-9, rtol=1e-9), float((fast - ref).abs().max())
    # each station's columns move only its own rows
    names = free.names
    k = names.index("instrument[B].tx")
    rows = fast[:, k].reshape(m.n, 3).abs().sum(1) > 0
    assert torch.equal(rows, m.station == 1)


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "torchcal", *args], cwd=cwd, capture_output=True, text=True)


@pytest.mark.slow
def test_cli_stations_and_probes_end_to_end(tmp_path):
    """simulate --stations 3 --probes 2, calibrate, predict: held-out and test errors within 1.2x those of the true
    model on the same poses; report.json names every station and probe."""
    r = _cli("simulate", "--robot", "ur5", "--out", "sim", "--seed", "4", "--poses", "240", "--test-poses", "60",
             "--stations", "3", "--probes", "2", "--quiet", cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = _cli("calibrate", "sim/train.csv", "--robot", "ur5", "--out", "cal", "--method", "kinematic", "--quiet",
             cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "cal" / "report.json").read_text())
    assert list(report["stations"]) == ["S1", "S2", "S3"] and list(report["probes"]) == ["P1", "P2"]
    assert all(s["n_holdout"] > 0 and s["n_train"] > 0 for s in report["stations"].values())
    r = _cli("predict", "cal", "sim/test.csv", "--out", "pred.csv", "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    test = read_measurements(tmp_path / "sim" / "test.csv")
    pred = read_measurements(tmp_path / "pred.csv", require_positions=True)
    err = float((pred.p - test.p).norm(dim=1).square().mean().sqrt())
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    sigma = truth["noise"]["tracker_sigma_m"]
    floor = (3 * sigma**2 + (15e-6) ** 2) ** 0.5  # tracker noise and about 15 um of joint noise at the probe
    assert err < 1.2 * floor, (err, floor)
    assert report["rmse_after_mm"] * 1e-3 < 1.2 * floor


@pytest.mark.slow
def test_stations_together_beat_alone_and_one_pose_fails():
    """Three placements with 60 poses each: calibrated together the shared geometry predicts each station's test
    poses better than each station calibrated alone; the same rows with one instrument pose (no station column) fail
    by orders of magnitude (the issue's 664 mm campaign)."""
    import dataclasses

    import torchcal
    from torchcal.pipeline import Options
    from torchcal.sim import SimConfig, simulate

    c = simulate(SimConfig(robot="ur5", poses=180, test_poses=90, seed=5, stations=3))
    opts = Options(method="kinematic")
    together = torchcal.calibrate("ur5", c.train, opts).model

    def rms(model, m):
        with torch.no_grad():
            return float((model(Context.from_measurements(m)) - m.p).norm(dim=1).square().mean().sqrt())

    joint = rms(together, c.test)
    alone = []
    for k in range(3):
        tr = c.train.subset(c.train.station == k)
        te = c.test.subset(c.test.station == k)
        plain = dataclasses.replace(tr, station=None, station_names=())
        model = torchcal.calibrate("ur5", plain, opts).model
        alone.append(rms(model, dataclasses.replace(te, station=None, station_names=())) ** 2 * te.n)
    alone = (sum(alone) / c.test.n) ** 0.5
    assert joint < alone, (joint, alone)
    from torchcal.errors import EstimationError

    # one instrument pose for three placements: the geometric fit would need corrections of metres, and says so
    with pytest.raises(EstimationError, match="many times their a-priori size"):
        torchcal.calibrate("ur5", dataclasses.replace(c.train, station=None, station_names=()), opts)


def test_a_robot_without_masses_and_with_a_readings_map_calibrates_from_two_stations():
    """The closed loop's lumped-compliance candidates project off the geometry's span, which the parameter
    Jacobian computes without a station per row: it takes the first station's frame there (this crashed)."""
    from pathlib import Path

    from torchcal._threads import torch_threads
    from torchcal.pipeline import Options, calibrate
    from torchcal.sim import SimConfig, simulate

    robot = str(Path(__file__).resolve().parents[1] / "robot" / "data" / "fanuc_like.yaml")
    c = simulate(SimConfig(robot=robot, poses=160, test_poses=10, seed=2, stations=2))
    with torch_threads(1):
        run = calibrate(robot, c.train, Options(seed=2))
    assert run.robot.stations == ("S1", "S2") and run.stage("geometric").rmse < 0.5 * run.stage("nominal").rmse


def test_full_pose_from_two_stations_and_two_probes_within_1_2x_of_the_true_model():
    """A 6-D probe measured from two placements with two targets: one calibration, each row's orientation whitened by
    its own sigma and seen from its own station; held-out position and orientation errors within 1.2x and 1.5x of
    the true model's on the same poses (the noise)."""
    import math

    from torchcal.estimate.fit import errors, orientation_errors
    from torchcal.pipeline import Options, calibrate
    from torchcal.sim import SimConfig, simulate

    c = simulate(
        SimConfig(robot="ur5", poses=240, test_poses=60, seed=4, stations=2, probes=2, orientation_sigma_deg=0.001)
    )
    assert c.train.r is not None and c.train.station_names == ("S1", "S2") and "orientation" in c.truth
    run = calibrate("ur5", c.train, Options(method="kinematic", seed=4))

    def rms(e):
        return float(e.square().mean().sqrt())

    test = c.test
    with torch.no_grad():
        truth_pos = rms(errors(c.model, test, trajectory=False))
        truth_ori = rms(orientation_errors(c.model, test, False))
    assert rms(errors(run.model, test, trajectory=False)) < 1.2 * truth_pos
    assert rms(orientation_errors(run.model, test, False)) < 1.5 * truth_ori
    assert math.degrees(truth_ori) < 0.005


@pytest.mark.slow
def test_a_residual_field_of_one_station_gets_its_own_learned_correction(tmp_path):
    """Two placements of one robot, the second's rows carrying a residual field the first's do not (another day, the
    tracker's own error): the default method takes one learned correction per station, predict applies each row's,
    and compensate at the second station's frame reaches its targets through that station's correction."""
    import dataclasses

    from torchcal.sim import SimConfig, simulate

    c = simulate(SimConfig(robot="ur5", poses=500, test_poses=100, seed=5, stations=2))

    def warp(m):
        s2 = (m.station == 1).to(torch.float64)[:, None]
        f = torch.stack([torch.sin(2 * m.q[:, 1]), torch.cos(2 * m.q[:, 2]), torch.sin(m.q[:, 0] + m.q[:, 3])], 1)
        return dataclasses.replace(m, p=m.p + 2e-4 * s2 * f)

    train, test = warp(c.train), warp(c.test)
    write_measurements(tmp_path / "train.csv", train)
    write_measurements(tmp_path / "test.csv", test)
    r = _cli("calibrate", "train.csv", "--robot", "ur5", "--out", "cal", "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert '"class": "GroupedCorrection"' in (tmp_path / "cal" / "model.json").read_text()
    r = _cli("predict", "cal", "test.csv", "--out", "pred.csv", "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    pred = read_measurements(tmp_path / "pred.csv", require_positions=True)
    err = (pred.p - test.p).norm(dim=1)
    s2 = test.station == 1
    assert float(err[s2].square().mean().sqrt()) < 0.3 * 2e-4  # the field (about 0.2 mm) is taken out at S2
    write_measurements(tmp_path / "targets.csv", dataclasses.replace(test.subset(torch.nonzero(s2).flatten())))
    r = _cli("compensate", "cal", "targets.csv", "--out", "comp.csv", "--station", "S2", "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "unreachable" not in r.stderr
