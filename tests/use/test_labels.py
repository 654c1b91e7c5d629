"""A run of one instrument pose or one lever arm knows the station and probe its rows named: ``predict``,
``compensate``, ``station`` and the fleet's prior lines refuse rows of another (exit 2, file, line and column)
instead of predicting them in the run's frame with its lever arm, metres off and without a word. Found by chaining
``calibrate --prior`` of a two-station run on rows of one station with ``predict`` of the other's rows (3.3 m off)."""

import json

import pytest
import torch

from torchcal.cli import main
from torchcal.data import read_measurements, write_measurements

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """A two-station, two-probe campaign, a run of its S1 / P1 rows alone, and its test rows by label."""
    root = tmp_path_factory.mktemp("labels")
    sim = root / "sim"
    args = ["simulate", "--robot", "ur5", "--out", str(sim), "--seed", "3", "--poses", "60", "--test-poses", "20"]
    assert main([*args, "--stations", "2", "--probes", "2", "--effect", "compliance:2=200um", "--quiet"]) == 0
    train = read_measurements(sim / "train.csv", require_positions=True)
    test = read_measurements(sim / "test.csv", require_positions=True)
    s1p1 = torch.nonzero((train.station == 0) & (train.probe == 0)).flatten()
    write_measurements(root / "s1p1.csv", train.subset(s1p1))
    run = root / "run"
    args = ["calibrate", str(root / "s1p1.csv"), "--robot", "ur5", "--method", "kinematic", "--out", str(run)]
    assert main([*args, "--quiet"]) == 0
    files = {}
    for name, rows in {
        "S1P1": (test.station == 0) & (test.probe == 0),
        "S2P1": (test.station == 1) & (test.probe == 0),
        "S1P2": (test.station == 0) & (test.probe == 1),
    }.items():
        files[name] = root / f"test-{name}.csv"
        write_measurements(files[name], test.subset(torch.nonzero(rows).flatten()))
    return root, sim, run, files


def _refused(capsys, args: list[str], out, column: str, label: str) -> None:
    assert main([*args, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"column '{column}'" in err and f"{column} '{label}'" in err and "line " in err, err
    assert not out.exists()


def test_the_run_records_its_one_station_and_probe(cell):
    _, _, run, _ = cell
    meta = json.loads((run / "model.json").read_text())
    assert meta["labels"] == {"station": "S1", "probe": "P1"}
    assert "stations" not in meta and "probes" not in meta


def test_predict_and_compensate_refuse_another_station_or_probe(cell, tmp_path, capsys):
    _, _, run, files = cell
    out = tmp_path / "pred.csv"
    assert main(["predict", str(run), str(files["S1P1"]), "--out", str(out), "--quiet"]) == 0
    pred, truth = read_measurements(out, require_positions=True), read_measurements(files["S1P1"])
    assert float((pred.p - truth.p).norm(dim=-1).max()) < 1e-3  # its own placement and probe: sub-millimetre
    for name, column, label in (("S2P1", "station", "S2"), ("S1P2", "probe", "P2")):
        out = tmp_path / f"pred-{name}.csv"
        _refused(capsys, ["predict", str(run), str(files[name]), "--out", str(out)], out, column, label)
        out = tmp_path / f"q-{name}.csv"
        _refused(capsys, ["compensate", str(run), str(files[name]), "--out", str(out)], out, column, label)


def test_a_new_placement_is_restationed_with_the_same_probe_only(cell, tmp_path, capsys):
    """``station`` on points of S2 (the run's probe P1): the new run predicts S2's rows and refuses S1's; points of
    another probe are refused, as its lever arm is not the run's."""
    _, _, run, files = cell
    s2 = read_measurements(files["S2P1"], require_positions=True)
    write_measurements(tmp_path / "points.csv", s2.subset(torch.arange(6)))
    st = tmp_path / "restationed"
    assert main(["station", str(run), str(tmp_path / "points.csv"), "--out", str(st), "--quiet"]) == 0
    meta = json.loads((st / "model.json").read_text())
    assert meta["station"]["label"] == "S2" and meta["labels"] == {"probe": "P1"}
    out = tmp_path / "pred.csv"
    assert main(["predict", str(st), str(files["S2P1"]), "--out", str(out), "--quiet"]) == 0
    pred = read_measurements(out, require_positions=True)
    assert float((pred.p - s2.p).norm(dim=-1).max()) < 1e-3
    out = tmp_path / "pred-s1.csv"
    _refused(capsys, ["predict", str(st), str(files["S1P1"]), "--out", str(out)], out, "station", "S1")
    p2 = read_measurements(files["S1P2"], require_positions=True)
    write_measurements(tmp_path / "points-p2.csv", p2.subset(torch.arange(6)))
    out = tmp_path / "restationed-p2"
    _refused(capsys, ["station", str(run), str(tmp_path / "points-p2.csv"), "--out", str(out)], out, "probe", "P2")


@pytest.mark.slow
def test_an_update_on_one_stations_rows_refuses_the_other_stations(cell, tmp_path, capsys):
    """``calibrate --prior`` of a two-station run on 10 rows of S1: the update is a run of S1, and S2's rows are
    refused (they were predicted 3.3 m off)."""
    _, sim, _, files = cell
    both = tmp_path / "both"
    args = ["calibrate", str(sim / "train.csv"), "--robot", "ur5", "--method", "kinematic", "--out", str(both)]
    assert main([*args, "--quiet"]) == 0
    s1 = read_measurements(files["S1P1"], require_positions=True)
    write_measurements(tmp_path / "update.csv", s1.subset(torch.arange(10)))
    upd = tmp_path / "upd"
    args = ["calibrate", str(tmp_path / "update.csv"), "--robot", "ur5", "--prior", str(both), "--out", str(upd)]
    assert main([*args, "--quiet"]) == 0
    out = tmp_path / "pred.csv"
    _refused(capsys, ["predict", str(upd), str(sim / "test.csv"), "--out", str(out)], out, "station", "S2")


def test_the_runs_own_names_may_be_given(cell, tmp_path, capsys):
    """``compensate`` and ``plan --run`` take ``--station S1 --probe P1`` on the run of S1 / P1 (its own names) and
    refuse another's."""
    _, _, run, files = cell
    out = tmp_path / "q.csv"
    args = ["compensate", str(run), str(files["S1P1"]), "--out", str(out), "--station", "S1", "--probe", "P1"]
    assert main([*args, "--quiet"]) == 0 and out.exists()
    out = tmp_path / "plan.csv"
    args = ["plan", "--run", str(run), "--n", "12", "--pool", "200", "--seed", "0", "--out", str(out)]
    assert main([*args, "--station", "S1", "--probe", "P1", "--quiet"]) == 0 and out.exists()
    out2 = tmp_path / "plan2.csv"
    args[-1] = str(out2)
    assert main([*args, "--station", "S2", "--quiet"]) == 2 and not out2.exists()
    assert "S2" in capsys.readouterr().err


def test_an_update_refuses_another_robot_than_the_priors(cell, tmp_path, capsys):
    """``calibrate --prior RUN --robot FILE`` where FILE is not the prior run's robot (its upper arm 0.5 m instead of
    0.425, the name still ur5; or another arm): refused, nothing written. The update starts from the prior run's
    robot, so the file was ignored while report.json named it."""
    from pathlib import Path

    import torchcal

    _, _, run, files = cell
    text = (Path(torchcal.__file__).resolve().parents[1] / "robots" / "ur5.yaml").read_text()
    assert "a: -0.425," in text
    (tmp_path / "ur5_other.yaml").write_text(text.replace("a: -0.425,", "a: -0.500,"))
    for robot, why in ((str(tmp_path / "ur5_other.yaml"), "mm from the prior run"), ("panda", "7 joints")):
        out = tmp_path / f"upd-{Path(robot).stem}"
        args = ["calibrate", str(files["S1P1"]), "--robot", robot, "--prior", str(run), "--out", str(out), "--quiet"]
        assert main(args) == 2 and not out.exists()
        err = capsys.readouterr().err
        assert "is not the robot of the prior run" in err and why in err, err
    ok = tmp_path / "upd-ur5"
    args = ["calibrate", str(files["S1P1"]), "--robot", "ur5", "--prior", str(run), "--out", str(ok), "--quiet"]
    assert main(args) == 0
