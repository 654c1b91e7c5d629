"""How far to trust a prediction: predict and compensate write sx, sy, sz and extrapolation per row, warn for rows
outside the calibrated region, and compensate there with the geometry and physical effects alone."""

import csv
import math

import pytest
import torch
from _cli import cli_simulate

from torchcal.cli import main
from torchcal.compensate import compensate, compensate_in_region, geometry_and_physics
from torchcal.effects import Context, LearnedEffect, MeasurementModel
from torchcal.effects.joint import FADE_LENGTH
from torchcal.effects.learned import CorrectionNet
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.report import load_covariance, load_model
from torchcal.robot import load_robot

F64 = torch.float64


def _rows(path):
    with open(path, encoding="utf-8") as f:
        return list(csv.DictReader(line for line in f if not line.startswith("#")))


@pytest.fixture(scope="module")
def kinematic_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("trust")
    assert cli_simulate(root / "sim", "--poses", "150", "--test-poses", "20", "--seed", "11") == 0
    assert main(["calibrate", str(root / "sim" / "train.csv"), "--robot", "ur5", "--method", "kinematic",
                 "--out", str(root / "run"), "--seed", "1", "--quiet"]) == 0  # fmt: skip
    return root


def _push_beyond(root, delta: float, joint: int = 2):
    """The test file with its first row's joint pushed ``delta`` beyond the training range of that joint."""
    train = _rows(root / "sim" / "train.csv")
    hi = max(float(r[f"q{joint}"]) for r in train)
    src = (root / "sim" / "test.csv").read_text(encoding="utf-8").splitlines()
    head = next(i for i, line in enumerate(src) if not line.startswith("#"))
    cols = src[head].split(",")
    first = src[head + 1].split(",")
    first[cols.index(f"q{joint}")] = repr(hi + delta)
    src[head + 1] = ",".join(first)
    out = root / f"beyond_{delta}.csv"
    out.write_text("\n".join(src) + "\n", encoding="utf-8")
    return out


def test_predict_writes_a_standard_deviation_and_the_extrapolation_of_every_row(kinematic_run, capsys):
    root = kinematic_run
    data = _push_beyond(root, 0.3)
    pred = root / "pred.csv"
    assert main(["predict", str(root / "run"), str(data), "--out", str(pred)]) == 0
    rows = _rows(pred)
    assert {"sx", "sy", "sz", "extrapolation"} <= set(rows[0])
    ext = [float(r["extrapolation"]) for r in rows]
    assert ext[0] == pytest.approx(0.3, abs=1e-9)  # joint 2 is the joint furthest out on the first row
    sig = torch.tensor([[float(r[k]) for k in ("sx", "sy", "sz")] for r in rows], dtype=F64)
    # through the parameters alone: positive, and well below the tracker noise (10 um) with 150 poses
    assert bool((sig > 0).all()) and float(sig.max()) < 10e-6
    err = capsys.readouterr().err
    assert "line" in err and "beyond the calibrated region" in err and err.count("warning") == sum(e > 0 for e in ext)


def test_the_predicted_deviation_is_the_covariance_carried_to_the_pose(kinematic_run):
    """A Monte Carlo check of sx, sy, sz: parameter vectors drawn from the stored covariance, the spread of the
    predictions they give at a few poses."""
    from torchcal.estimate.covariance import prediction_std

    run = kinematic_run / "run"
    model, _ = load_model(run)
    cov = load_covariance(run, model)
    assert cov is not None and cov.matrix.shape[0] == len(cov.labels) > 10
    q = torch.tensor([float(r[f"q{j}"]) for r in _rows(kinematic_run / "sim" / "test.csv")[:4] for j in range(1, 7)],
                     dtype=F64).reshape(4, 6)  # fmt: skip
    ctx = Context(q=q)
    sd = prediction_std(model, ctx, cov)
    free = cov.free(model)
    x0 = free.vector()
    g = torch.Generator().manual_seed(0)
    L = torch.linalg.cholesky(cov.matrix + 1e-30 * torch.eye(len(x0), dtype=F64))
    draws = []
    with torch.no_grad():
        for _ in range(400):
            free.assign(x0 + L @ torch.randn(len(x0), generator=g, dtype=F64))
            draws.append(model(ctx))
    free.assign(x0)
    mc = torch.stack(draws).std(0)
    torch.testing.assert_close(sd, mc, rtol=0.15, atol=0)  # 400 draws: the spread to about 4 %


def test_a_damaged_covariance_is_refused_naming_the_file(kinematic_run, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(kinematic_run / "run", run)
    model, _ = load_model(run)
    state = torch.load(run / "covariance.pt", weights_only=True)
    state["covariance"] = state["covariance"][:-1]
    torch.save(state, run / "covariance.pt")
    with pytest.raises(Exception, match="covariance.pt"):
        load_covariance(run, model)
    state = torch.load(kinematic_run / "run" / "covariance.pt", weights_only=True)
    state["names"] = ["robot.geometry.nothing_here"] + state["names"][1:]
    torch.save(state, run / "covariance.pt")
    assert main(["predict", str(run), str(kinematic_run / "sim" / "test.csv"), "--out", str(tmp_path / "p.csv")]) == 2
    assert not (tmp_path / "p.csv").exists()
    torch.save(_Payload(), run / "covariance.pt")  # a pickled object: never unpickled
    with pytest.raises(Exception, match="covariance.pt holds more than tensors"):
        load_covariance(run, model)


class _Payload:
    pass


def test_parameter_covariance_state_round_trip():
    model = MeasurementModel(load_robot("ur5"))
    params = dict(model.named_parameters())
    name = next(n for n in params if n.startswith("robot.geometry"))
    C = torch.tensor([[4.0, 1.0], [1.0, 9.0]], dtype=F64) * 1e-10
    cov = ParameterCovariance([name], [[0, 1]], ["a", "b"], C)
    back = ParameterCovariance.from_state(cov.state(), model)
    assert back.names == [name] and torch.equal(back.matrix, C)
    for bad in (C * float("nan"), -C, C + torch.tensor([[0.0, 1e-9], [0.0, 0.0]], dtype=F64)):
        with pytest.raises(ValueError):
            ParameterCovariance.from_state({**cov.state(), "covariance": bad}, model)


# ---------------------------------------------------------------------------------- learned corrections fade


def _learned_model():
    torch.manual_seed(0)
    robot = load_robot("ur5")
    net = CorrectionNet(hidden=8)
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(3.0)
    model = MeasurementModel(robot, [LearnedEffect(net)])
    g = torch.Generator().manual_seed(1)
    q_train = (torch.rand(100, 6, generator=g, dtype=F64) - 0.5) * 1.2
    model.set_region(q_train, fade=True)
    return model, q_train


def test_a_learned_correction_is_whole_inside_the_region_and_gone_far_beyond_it():
    model, q_train = _learned_model()
    plain = geometry_and_physics(model)
    with torch.no_grad():
        inside = model(Context(q=q_train[:10])) - plain(Context(q=q_train[:10]))
        free = MeasurementModel(model.robot, list(model.effects))  # the same correction without a region
        torch.testing.assert_close(inside, free(Context(q=q_train[:10])) - plain(Context(q=q_train[:10])))
        far = q_train[:10].clone()
        far[:, 1] = float(q_train[:, 1].max()) + 6 * FADE_LENGTH
        assert float((model(Context(q=far)) - plain(Context(q=far))).norm(dim=1).max()) < 1e-6 * float(
            (free(Context(q=far)) - plain(Context(q=far))).norm(dim=1).max()
        )
    assert float(model.extrapolation(far)[0]) == pytest.approx(6 * FADE_LENGTH)
    assert float(model.extrapolation(q_train).max()) == 0.0


def test_compensate_outside_the_region_uses_geometry_and_physics_alone():
    model, q_train = _learned_model()
    q_in = q_train[:5] * 0.5  # well inside: a command near the edge may end just beyond it
    q_out = q_train[5:10].clone()
    q_out[:, 0] = float(q_train[:, 0].max()) + 0.4
    with torch.no_grad():
        targets = model(Context(q=torch.cat([q_in, q_out])))
    seed = torch.cat([q_in, q_out]) + 0.01
    res, ext, plain_rows = compensate_in_region(model, targets, seed)
    assert plain_rows.tolist() == [False] * 5 + [True] * 5
    assert bool((ext[5:] > 0).all()) and bool((ext[:5] == 0).all())
    full = compensate(model, targets[:5], seed[:5])
    plain = compensate(geometry_and_physics(model), targets[5:], seed[5:])
    torch.testing.assert_close(res.q[:5], full.q)
    torch.testing.assert_close(res.q[5:], plain.q)
    assert math.isfinite(float(res.miss.max()))
