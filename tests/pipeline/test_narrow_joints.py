"""A joint the training poses hardly moved is named at calibrate time: on stderr, in report.json and report.md."""

import json
import math

import pytest
import torch

from torchcal.cli import main
from torchcal.pipeline.checks import NARROW_DEG, narrow_joints, narrow_note

F64 = torch.float64


def test_known_answers_revolute_and_prismatic():
    g = torch.Generator().manual_seed(0)
    q = torch.rand(50, 3, generator=g, dtype=F64)
    q[:, 0] *= math.radians(1.0)  # 1 deg: narrow
    q[:, 1] *= math.radians(5 * NARROW_DEG)  # about 25 deg of a turn: not narrow
    q[:, 2] *= 0.02  # a 3 m track moved 2 cm: under 3 % of its limits
    limits = torch.tensor([[-2 * math.pi, 2 * math.pi], [-math.pi, math.pi], [0.0, 3.0]], dtype=F64)
    got = narrow_joints(q, limits, ("revolute", "revolute", "prismatic"))
    assert [n.joint for n in got] == [1, 3]
    assert got[0].unit == "deg" and got[0].range == pytest.approx(math.degrees(float(q[:, 0].max() - q[:, 0].min())))
    assert got[0].limits == pytest.approx(360.0)  # clipped to a turn
    assert got[1].unit == "m" and got[1].limits == pytest.approx(3.0)
    note = narrow_note(got)
    assert "q1 moved" in note and "q3 moved" in note and "beyond" not in note.split(".")[0]
    assert narrow_note([]) is None


def test_a_joint_small_against_its_limits_is_narrow_though_over_a_few_degrees():
    q = torch.linspace(0.0, math.radians(8.0), 20, dtype=F64)[:, None]
    limits = torch.tensor([[-math.pi, math.pi]], dtype=F64)
    assert [n.joint for n in narrow_joints(q, limits, ("revolute",))] == [1]  # 8 deg of 360: 2.2 %
    wide = torch.linspace(0.0, math.radians(12.0), 20, dtype=F64)[:, None]
    assert narrow_joints(wide, limits, ("revolute",)) == []


@pytest.mark.slow
def test_calibrate_names_the_narrow_joints(tmp_path, capsys):
    sim, run = tmp_path / "sim", tmp_path / "run"
    assert (
        main(
            ["simulate", "--robot", "ur5", "--out", str(sim), "--poses", "150", "--test-poses", "10"]
            + ["--narrow", "1,4,5,6", "--seed", "2"]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(["calibrate", str(sim / "train.csv"), "--robot", "ur5", "--method", "kinematic", "--out", str(run)]) == 0
    )
    err = capsys.readouterr().err
    assert "warning: narrow training range: q1 moved" in err and "q6 moved" in err and "q2 moved" not in err
    report = json.loads((run / "report.json").read_text())
    assert [n["joint"] for n in report["region"]["narrow_joints"]] == [1, 4, 5, 6]
    assert all(n["range"] < 1.01 and n["unit"] == "deg" for n in report["region"]["narrow_joints"])
    story = (run / "report.md").read_text().split("## The story")[1].split("\n## ")[0]
    assert "Narrow training range: q1 moved" in story


@pytest.mark.slow
def test_a_campaign_over_the_workspace_names_none(tmp_path, capsys):
    sim, run = tmp_path / "sim", tmp_path / "run"
    assert main(["simulate", "--robot", "ur5", "--out", str(sim), "--poses", "150", "--test-poses", "10"]) == 0
    assert (
        main(["calibrate", str(sim / "train.csv"), "--robot", "ur5", "--method", "kinematic", "--out", str(run)]) == 0
    )
    assert "narrow" not in capsys.readouterr().err
    assert json.loads((run / "report.json").read_text())["region"]["narrow_joints"] == []
