"""Narrow campaigns: held joints stay in their band in training, the test poses range, a compliance by its value."""

import json
import math
import subprocess
import sys

import pytest
import torch

from torchcal.errors import OptionError
from torchcal.sim import EffectSpec, SimConfig, simulate, visible


def _config() -> SimConfig:
    return SimConfig(
        robot="ur5",
        poses=120,
        test_poses=80,
        seed=5,
        narrow=(1, 4, 5, 6),
        narrow_width_deg=1.0,
        effects=[EffectSpec.parse("compliance:2=1.5e-5rad/Nm")],
    )


@pytest.fixture(scope="module")
def narrow():
    return simulate(_config())


def test_held_joints_stay_within_their_band_and_the_others_range(narrow):
    q = torch.rad2deg(narrow.train.q)
    span = q.max(0).values - q.min(0).values
    held = torch.tensor([0, 3, 4, 5])
    # the band is 1 deg wide; the readings add 0.0005 deg of noise
    assert bool((span[held] <= 1.0 + 0.01).all()), span
    assert bool((span[held] > 0.5).all()), span
    assert float(span[1]) > 90 and float(span[2]) > 90, span
    ranges = narrow.truth["narrow"]["train_range_deg"]
    assert narrow.truth["narrow"]["joints"] == [1, 4, 5, 6]
    assert ranges[0][1] - ranges[0][0] == pytest.approx(float(span[0]), abs=0.01)


def test_test_poses_range_over_the_workspace_and_are_visible(narrow):
    q = narrow.test.q
    span = torch.rad2deg(q.max(0).values - q.min(0).values)
    assert bool((span > 90).all()), span
    truth = narrow.model.robot
    tracker = torch.tensor(narrow.truth["instrument"]["tracker_in_base_m"])
    seen = visible(truth, narrow.q_true, tracker, truth.tool.nominal)
    assert float(seen.double().mean()) > 0.95  # planned with the nominal robot: a pose at the edge may flip


def test_a_compliance_given_by_its_value_keeps_it(narrow):
    (eff,) = narrow.truth["effects"]
    assert eff["params"]["k_rad_per_Nm"] == pytest.approx(1.5e-5)
    assert eff["size_m"] == pytest.approx(eff["rms_m"], rel=1e-9)
    assert eff["rms_m"] > 1e-4  # joint 2 of a UR5 at 1.5e-5 rad/Nm sags by tenths of a millimetre


def test_the_same_seed_gives_the_same_narrow_campaign(narrow):
    again = simulate(_config())
    assert torch.equal(again.train.q, narrow.train.q) and torch.equal(again.test.p, narrow.test.p)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"narrow": (1, 1)},
        {"narrow": (0,)},
        {"narrow": (2,), "narrow_width_deg": 0.0},
        {"narrow": (2,), "trajectory": True},
        {"narrow": (2,), "stations": 2},
    ],
)
def test_bad_narrow_settings_are_refused(kwargs):
    with pytest.raises(OptionError):
        SimConfig(**kwargs)


def test_a_joint_beyond_the_robot_is_refused():
    with pytest.raises(OptionError, match="narrow joint 7"):
        simulate(SimConfig(robot="ur5", poses=10, test_poses=0, narrow=(7,)))


def test_rad_per_nm_is_for_a_compliance_only():
    with pytest.raises(OptionError, match="only a compliance"):
        EffectSpec.parse("backlash:2=1e-5rad/Nm")
    assert EffectSpec.parse("compliance:3=2e-5rad/Nm").k == pytest.approx(2e-5)


def test_the_command_writes_a_narrow_campaign(tmp_path):
    out = tmp_path / "c"
    cmd = [sys.executable, "-m", "torchcal", "simulate", "--robot", "ur5", "--out", str(out), "--poses", "60"]
    cmd += ["--test-poses", "20", "--narrow", "1,4,5,6", "--width-deg", "2"]
    subprocess.run(cmd, check=True, capture_output=True)
    truth = json.loads((out / "truth.json").read_text())
    ranges = truth["narrow"]["train_range_deg"]
    assert all(ranges[j][1] - ranges[j][0] <= 2.01 for j in (0, 3, 4, 5))
    assert not math.isclose(ranges[1][0], ranges[1][1])
    bad = subprocess.run(cmd[:-4] + ["--width-deg", "2"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--narrow" in bad.stderr
