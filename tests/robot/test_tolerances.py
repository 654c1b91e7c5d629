"""A robot file's manufacturing tolerances (``tolerances:`` of a DH table, issue 51): the priors of its kinematic
calibration, refused where they are not two positive numbers in range."""

import math
from pathlib import Path

import pytest

from torchcal.errors import RobotSpecError
from torchcal.pipeline import Options, calibrate
from torchcal.robot import load_robot
from torchcal.sim import SimConfig, simulate

UR5 = Path(__file__).resolve().parents[2] / "robots" / "ur5.yaml"


def _with(tmp_path, block: str) -> Path:
    out = tmp_path / "ur5_tol.yaml"
    out.write_text(UR5.read_text(encoding="utf-8") + "\n" + block + "\n", encoding="utf-8")
    return out


def test_a_dh_table_declares_its_tolerances_and_the_kinematic_calibration_uses_them(tmp_path):
    path = _with(tmp_path, "tolerances: {length_mm: 0.05, angle_deg: 0.02}")
    robot = load_robot(path)
    assert robot.tolerances == pytest.approx((5e-5, math.radians(0.02)), rel=1e-12)
    assert load_robot(UR5).tolerances is None
    c = simulate(SimConfig(robot="ur5", poses=60, test_poses=5, seed=0))
    run = calibrate(path, c.train, Options(method="kinematic", seed=0))
    fit = run.options.fit.geometric()
    assert (fit.prior_length, fit.prior_angle) == pytest.approx((5e-5, math.radians(0.02)), rel=1e-12)
    assert run.options.fit.prior_length == Options().fit.prior_length  # the later fits keep their own priors


@pytest.mark.parametrize(
    "block, words",
    [
        ("tolerances: {length_mm: 0.1}", "length_mm and angle_deg"),
        ("tolerances: {length_mm: 0.1, angle_deg: 0.01, x: 1}", "length_mm and angle_deg"),
        ("tolerances: {length_mm: -0.1, angle_deg: 0.01}", "'length_mm' = -0.1 must be above 0"),
        ("tolerances: {length_mm: 0.1, angle_deg: 5}", "'angle_deg' = 5.0 must be above 0 and at most 1.0"),
        ("tolerances: {length_mm: abc, angle_deg: 0.01}", "'length_mm' must be a number"),
        ("tolerances: 0.1", "must be a mapping"),
    ],
)
def test_bad_tolerances_are_refused_naming_the_file(tmp_path, block, words):
    path = _with(tmp_path, block)
    with pytest.raises(RobotSpecError, match="ur5_tol.yaml") as e:
        load_robot(path)
    assert words in str(e.value)
