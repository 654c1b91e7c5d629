"""The load columns end to end (issue 45): simulate --test-payload/--torques writes them, predict keeps them and
flags the rows whose load the run was not fitted at (stderr, the conditions and extrapolation columns)."""

import json

import pytest
from _cli import cli_simulate

import torchcal
from torchcal.cli import main


@pytest.mark.slow  # about 7 s: a campaign, a kinematic run and two predictions
def test_predict_flags_rows_beyond_the_training_load(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert (
        cli_simulate(sim, "--poses", "40", "--test-poses", "6", "--test-payload", "10", "--torques", robot="ur10") == 0
    )
    truth = json.loads((sim / "truth.json").read_text())
    assert truth["load"]["payload_train_kg"] == [0.0] and truth["load"]["payload_test_kg"] == [10.0]
    run = tmp_path / "run"
    args = ["calibrate", str(sim / "train.csv"), "--robot", "ur10", "--out", str(run), "--method", "kinematic"]
    assert main([*args, "--quiet"]) == 0
    assert json.loads((run / "model.json").read_text())["load"]["payload_kg"] == [0.0, 0.0]
    capsys.readouterr()
    assert main(["predict", str(run), str(sim / "test.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    assert "6 of 6 rows carry a load the run was not fitted at" in capsys.readouterr().err
    text = (tmp_path / "p.csv").read_text()
    assert text.count(",load beyond training") == 6
    out = torchcal.read_measurements(tmp_path / "p.csv", require_positions=False)  # reads back as measurements
    assert out.payload.tolist() == [10.0] * 6 and out.tau.shape == (6, 6)
    assert bool((out.extra["extrapolation"] > 0).all())
    assert main(["predict", str(run), str(sim / "train.csv"), "--out", str(tmp_path / "t.csv")]) == 0
    assert "not fitted at" not in capsys.readouterr().err
    assert (tmp_path / "t.csv").read_text().count(",trained") == 40
    capsys.readouterr()
    assert main(["compensate", str(run), str(sim / "test.csv"), "--out", str(tmp_path / "c.csv")]) == 0
    assert "6 of 6 rows carry a load the run was not fitted at" in capsys.readouterr().err
    assert (tmp_path / "c.csv").read_text().count(",load beyond training,") == 6
    assert (
        main(["compensate", str(run), str(sim / "test.csv"), "--payload", "0", "--out", str(tmp_path / "c0.csv")]) == 0
    )
    # --payload 0 is a trained payload, but the rows' torques (measured at 10 kg) still lie beyond the training ones
    assert (tmp_path / "c0.csv").read_text().count(",load beyond training,") == 6


def test_simulate_refuses_a_negative_payload(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli_simulate(tmp_path / "s", "--payload-levels", "0,-5")
    assert exit_.value.code == 2
    assert "payloads are masses >= 0 kg" in capsys.readouterr().err
