"""The torchcal command: simulate and demo, errors and exit codes."""

import json
import subprocess
import sys

import pytest
import torch
from _cli import cli_simulate

import torchcal
from torchcal.cli import main
from torchcal.errors import MeasurementFileError


def test_simulate_writes_the_contract_files(tmp_path, capsys):
    out = tmp_path / "sim"
    assert cli_simulate(out, "--seed", "1", "--poses", "120", "--effect", "compliance:2=50um") == 0
    assert sorted(p.name for p in out.iterdir()) == [".torchcal-run", "test.csv", "train.csv", "truth.json"]
    truth = json.loads((out / "truth.json").read_text())
    assert truth["effects"][0]["kind"] == "compliance" and truth["effects"][0]["joint"] == 2
    assert capsys.readouterr().out == ""  # results go to files, messages to stderr


def test_simulate_puts_in_a_coupling_by_its_ratio(tmp_path, capsys):
    out = tmp_path / "sim"
    assert cli_simulate(out, "--seed", "1", "--poses", "30", "--effect", "coupling:5<-4=-1e-3") == 0
    (effect,) = json.loads((out / "truth.json").read_text())["effects"]
    assert (effect["kind"], effect["joint"], effect["source"]) == ("coupling", 5, 4)
    assert effect["params"]["c"] == pytest.approx(-1e-3, rel=1e-12)
    assert cli_simulate(tmp_path / "bad", "--effect", "cyclic:2=1e-3") == 2
    assert "give the size with a unit" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_simulate_in_millimetres_reads_back_with_the_unit_option(tmp_path):
    cli_simulate(tmp_path / "m", "--seed", "2", "--poses", "50")
    cli_simulate(tmp_path / "mm", "--seed", "2", "--poses", "50", "--length-unit", "mm")
    a = torchcal.read_measurements(tmp_path / "m" / "train.csv")
    b = torchcal.read_measurements(tmp_path / "mm" / "train.csv", length_unit="mm")
    assert torch.allclose(a.p, b.p, rtol=1e-15, atol=0)
    with pytest.raises(MeasurementFileError, match="length-unit mm"):
        torchcal.read_measurements(tmp_path / "mm" / "train.csv")


def test_simulate_trajectory_and_urdf_robot(tmp_path):
    out = tmp_path / "traj"
    assert (
        cli_simulate(
            out, "--trajectory", "--samples", "400", "--train-samples", "300", "--seed", "3", robot="panda.urdf"
        )
        == 0
    )
    m = torchcal.read_measurements(out / "train.csv")
    assert m.q.shape == (300, 7) and m.t is not None


def test_bad_options_exit_nonzero_and_write_nothing(tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["simulate", "--robot", "ur5", "--out", str(out), "--effect", "compliance:9"]) == 2
    assert "joint 9 is outside 1..6" in capsys.readouterr().err
    assert main(["simulate", "--robot", "ur77", "--out", str(out)]) == 2
    assert "built-ins" in capsys.readouterr().err
    assert not out.exists()


def test_demo_runs_and_reports(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo"), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "report:" in printed and str(tmp_path / "demo" / "run" / "report.md") in printed
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    truth = json.loads((tmp_path / "demo" / "data" / "truth.json").read_text())
    # the loop names the undeclared compliance of joint 2 (kind and joint as truth.json has them), then the
    # learned model takes the smooth field; each step lowers the held-out error
    assert [(e["kind"], e["joint"]) for e in truth["effects"]] == [("compliance", 2), ("learned", None)]
    assert summary["effects"] == [{"kind": "compliance", "joint": 2}, {"kind": "learned", "joint": None}]
    assert summary["stages"] == ["nominal", "geometric", "compliance(joint 2)", "learned"]
    rmse = [summary["holdout_rmse_mm"][s] for s in summary["stages"]]
    assert rmse == sorted(rmse, reverse=True) and rmse[1] > 1.5 * rmse[-1]
    assert summary["test_file_rmse_mm"] < 0.035
    report = json.loads((tmp_path / "demo" / "run" / "report.json").read_text())
    # one p per decision where a user reads it, its test named, and each parameter with its unit: the demo's line,
    # report.json's value and unit and the report's note agree
    k = report["effects"][0]["params"]["k"]
    assert k["unit"] == "rad/(N m)"
    p = report["effects"][0]["evidence"]["p_bonferroni"]
    assert "+ compliance(joint 2)" in printed and "effects found:\n" in printed
    assert (
        f"  compliance (joint 2): k = {k['value']:.3g} rad/(N m) ± {k['std']:.2g}; localisation of tau2: "
        f"Bonferroni p = {p:.2g}\n  learned\n"
    ) in printed
    assert any(
        n.startswith(f"diagnosis: compliance:2 added (localisation of tau2: Bonferroni p = {p:.2g}")
        for n in report["notes"]
    )
    from torchcal.report.consistency import contradictions

    assert contradictions(tmp_path / "demo" / "run", printed) == []
    assert (
        report["effects"][0]["kind"] == "compliance"
        and report["effects"][0]["rmse_after_mm"] < report["effects"][0]["rmse_before_mm"]
    )


def test_console_script_and_module_entry_points():
    for cmd in (["torchcal", "--help"], [sys.executable, "-m", "torchcal", "simulate", "--help"]):
        exe = (
            cmd
            if cmd[0] != "torchcal"
            else [str(__import__("pathlib").Path(sys.executable).parent / "torchcal"), "--help"]
        )
        r = subprocess.run(exe, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and "usage" in r.stdout
