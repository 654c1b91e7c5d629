"""How far to trust a prediction: predict and compensate write sx, sy, sz and extrapolation per row, warn for rows
outside the calibrated region, and compensate there with the geometry and physical effects alone."""

import csv
import json
import math

import pytest
import torch
from _cli import cli_simulate

from torchcal.cli import main
from torchcal.effects import Context, LearnedEffect, MeasurementModel
from torchcal.effects.joint import FADE_LENGTH
from torchcal.effects.learned import CorrectionNet
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.robot import load_robot
from torchcal.use.compensate import compensate, compensate_in_region, geometry_and_physics
from torchcal.use.rundir import load_covariance, load_model

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
    # a new measurement minus the prediction: at least the instrument's noise (the run's 15 um), and with a model that
    # leaves nothing unexplained not much more
    assert bool((sig >= 15e-6).all()) and float(sig.max()) < 40e-6
    assert {r["model"] for r in rows} == {"full"}  # a kinematic run has no other model to choose
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


# ------------------------------------------------------------------------- a sigma that covers the error


def _coverage(truth_csv, pred_csv):
    """The share of rows whose three |error| / sigma are all <= 3, and the median |error| / sigma."""
    t, p = _rows(truth_csv), _rows(pred_csv)
    e = torch.tensor([[float(a[k]) - float(b[k]) for k in "xyz"] for a, b in zip(t, p)], dtype=F64)
    s = torch.tensor([[float(b[k]) for k in ("sx", "sy", "sz")] for b in p], dtype=F64)
    z = e.abs() / s
    return float((z.amax(dim=1) <= 3).double().mean()), float(z.median())


@pytest.fixture(scope="module")
def unexplained_run(tmp_path_factory):
    """A kinematic calibration of a cell with a compliance it does not model (0.1 mm, many times the noise)."""
    root = tmp_path_factory.mktemp("unexplained")
    assert cli_simulate(root / "sim", "--poses", "250", "--test-poses", "150", "--seed", "12",
                        "--effect", "compliance:2=100um") == 0  # fmt: skip
    assert main(["calibrate", str(root / "sim" / "train.csv"), "--robot", "ur5", "--method", "kinematic",
                 "--out", str(root / "run"), "--seed", "1", "--quiet"]) == 0  # fmt: skip
    return root


def test_the_sigma_covers_what_the_model_leaves_unexplained(unexplained_run):
    root = unexplained_run
    pred = root / "pred.csv"
    assert main(["predict", str(root / "run"), str(root / "sim" / "test.csv"), "--out", str(pred), "--quiet"]) == 0
    share, median = _coverage(root / "sim" / "test.csv", pred)
    assert share >= 0.95 and 0.3 <= median <= 1.5, (share, median)
    # the parameters and the noise alone (the sigma before the run measured its unexplained level) do not cover it
    model, _ = load_model(root / "run")
    from torchcal.data import read_measurements
    from torchcal.estimate.covariance import combined_std

    test = read_measurements(root / "sim" / "test.csv")
    s = (
        combined_std(model, Context.from_measurements(test), load_covariance(root / "run", model)) ** 2 + 15e-6**2
    ).sqrt()
    with torch.no_grad():
        z = (model(Context.from_measurements(test)) - test.p).abs() / s
    assert float((z.amax(dim=1) <= 3).double().mean()) < 0.8
    trust = json.loads((root / "run" / "report.json").read_text(encoding="utf-8"))["trust"]["model"]
    assert trust["n_holdout"] > 20 and max(trust["unexplained_m"]) > 15e-6 and trust["coverage_3sigma"] >= 0.95


def test_a_run_written_before_the_level_still_predicts_and_says_so(unexplained_run, tmp_path, capsys):
    import shutil

    run = tmp_path / "old"
    shutil.copytree(unexplained_run / "run", run)
    meta = json.loads((run / "model.json").read_text(encoding="utf-8"))
    del meta["trust"]
    (run / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    capsys.readouterr()
    assert main(["predict", str(run), str(unexplained_run / "sim" / "test.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    assert "written before torchcal measured what its model leaves unexplained" in capsys.readouterr().err
    sig = torch.tensor([[float(r[k]) for k in ("sx", "sy", "sz")] for r in _rows(tmp_path / "p.csv")], dtype=F64)
    assert bool((sig > 0).all())  # the parameters' (the file's per-point noise is not in report.json)
    meta["trust"] = None  # a run with too few held-out rows to measure the level on
    (run / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    assert main(["predict", str(run), str(unexplained_run / "sim" / "test.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    assert "had fewer than 10 held-out rows" in capsys.readouterr().err
    meta["trust"] = {"noise_m": [1, 2]}
    (run / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    assert main(["predict", str(run), str(unexplained_run / "sim" / "test.csv"), "--out", str(tmp_path / "q.csv")]) == 2
    assert "model.json: trust: " in capsys.readouterr().err and not (tmp_path / "q.csv").exists()


def test_beyond_the_region_the_model_with_the_smaller_sigma_predicts(kinematic_run, tmp_path):
    """A run that keeps a kinematic calibration beside its model and chose no model for beyond the region (too few
    rows beyond to choose on: torchcal.pipeline.beyond): beyond the region, where the model's own sigma is the
    larger, the kinematic calibration predicts the row and the model column says so; inside, the model does."""
    import shutil

    from torchcal.estimate.trust import Trust

    run = tmp_path / "run"
    shutil.copytree(kinematic_run / "run", run)
    state = torch.load(run / "model.pt", weights_only=True)
    key = next(k for k in state if k.startswith("robot.instrument"))
    geo = dict(state)
    geo[key] = state[key] + 1e-3  # a different model, told apart by its predictions
    torch.save(geo, run / "geometric.pt")
    meta = json.loads((run / "model.json").read_text(encoding="utf-8"))
    level = Trust((15e-6,) * 3, (10e-6,) * 3, (10e-6,) * 3, 1.0, 30, 1.0, 0.6)
    meta["trust"] = {**level.to_dict(), "unexplained_far_m": [5e-3] * 3}  # sure inside, far less sure beyond
    meta["geometric"] = {"trust": {**level.to_dict(), "unexplained_m": [1e-4] * 3, "unexplained_far_m": [1e-4] * 3}}
    meta.pop("beyond", None)  # no choice made: the sigma rule
    (run / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    data = _push_beyond(kinematic_run, 0.3)
    _check_compensate_chooses(run, data, tmp_path)
    assert main(["predict", str(run), str(data), "--out", str(tmp_path / "p.csv"), "--quiet"]) == 0
    rows = _rows(tmp_path / "p.csv")
    which = [r["model"] for r in rows]
    assert which[0] == "geometric" and set(which[1:]) <= {"full", "geometric"}
    ext = [float(r["extrapolation"]) for r in rows]
    assert all(w == "full" for w, e in zip(which, ext) if e == 0)
    assert all(w == "geometric" for w, e in zip(which, ext) if e >= 0.1)
    assert main(["predict", str(kinematic_run / "run"), str(data), "--out", str(tmp_path / "k.csv"), "--quiet"]) == 0
    plain = _rows(tmp_path / "k.csv")
    for r, k in zip(rows, plain):  # the geometric rows predicted by geometric.pt: its instrument moved them
        moved = max(abs(float(r[c]) - float(k[c])) for c in "xyz")
        assert (moved > 1e-4) == (r["model"] == "geometric")
        if r["model"] == "geometric":
            assert float(r["sx"]) < 1e-3  # the geometric model's own sigma


def _check_compensate_chooses(run, data, tmp_path):
    """compensate on the targets the model puts at ``data``'s joints: a row beyond the region where the run's model is
    far less sure than its kinematic calibration is commanded by that one (its ``model`` says so, and the
    kinematic calibration puts the probe on the target there); the rows inside by the run's model."""
    from torchcal.data import read_measurements
    from torchcal.use.rundir import load_geometric

    model, meta = load_model(run)
    geo = load_geometric(run, model, meta)[0]
    q = read_measurements(data).q
    with torch.no_grad():
        targets = model(Context(q=q))
    lines = ["x,y,z"] + [",".join(repr(float(v)) for v in row) for row in targets]
    (tmp_path / "targets.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert main(["compensate", str(run), str(tmp_path / "targets.csv"), "--start", str(data),
                 "--out", str(tmp_path / "j.csv"), "--quiet"]) == 0  # fmt: skip
    rows = _rows(tmp_path / "j.csv")
    assert rows[0]["model"] == "geometric" and float(rows[0]["extrapolation"]) > 0.1
    qj = torch.tensor([[float(r[f"q{j}"]) for j in range(1, 7)] for r in rows], dtype=F64)
    with torch.no_grad():
        miss_geo = (geo(Context(q=qj)) - targets).norm(dim=1)
        miss_full = (model(Context(q=qj)) - targets).norm(dim=1)
    for k, r in enumerate(rows):
        if r["model"] == "geometric":
            assert float(miss_geo[k]) < 1e-6 and float(r["sx"]) < 1e-3
        elif r["status"] == "converged":
            assert r["model"] == "full" and float(miss_full[k]) < 1e-6
