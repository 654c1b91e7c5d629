"""A prismatic joint's column is a length: --length-unit scales it, --angle-unit does not, its limits are metres."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.data import read_measurements
from torchcal.errors import MeasurementFileError

TYPES = ("prismatic", "revolute", "revolute")
LIMITS = torch.tensor([[-1.0, 1.0], [-2 * math.pi, 2 * math.pi], [-2 * math.pi, 2 * math.pi]], dtype=torch.float64)


def write(tmp_path, rows):
    path = tmp_path / "track.csv"
    path.write_text("q1,q2,q3,x,y,z\n" + "\n".join(rows) + "\n")
    return path


def read(path, **kw):
    return read_measurements(path, dof=3, joint_limits=LIMITS, joint_types=TYPES, **kw)


def test_length_unit_scales_the_prismatic_column_and_angle_unit_does_not(tmp_path):
    mm_deg = write(tmp_path, ["750.0,90.0,-45.0,1500.0,250.0,750.0", "-250.0,30.0,120.0,1250.0,-500.0,500.0"])
    m = read(mm_deg, length_unit="mm", angle_unit="deg")
    deg = math.pi / 180
    expected = torch.tensor([[0.75, 90 * deg, -45 * deg], [-0.25, 30 * deg, 120 * deg]], dtype=torch.float64)
    torch.testing.assert_close(m.q, expected, rtol=1e-15, atol=0)
    torch.testing.assert_close(m.p[0], torch.tensor([1.5, 0.25, 0.75], dtype=torch.float64))
    # metres and degrees: the track reading is kept as it is, and a file of small angles in degrees is not taken for
    # radians because of the track's column
    m = read(write(tmp_path, ["0.75,90.0,-45.0,1.5,0.25,0.75", "-0.25,30.0,120.0,1.25,-0.5,0.5"]), angle_unit="deg")
    assert m.q[:, 0].tolist() == [0.75, -0.25]


def test_the_prismatic_column_is_not_judged_as_an_angle(tmp_path):
    # 0.9 m and 7 rad-looking numbers: a track of 10 m reads past 2 pi without looking like degrees
    long = torch.tensor([[-10.0, 10.0], [-2 * math.pi, 2 * math.pi], [-2 * math.pi, 2 * math.pi]], dtype=torch.float64)
    path = write(tmp_path, ["7.5,0.1,-0.2,1.5,0.25,0.75", "-6.5,0.3,0.2,1.25,-0.5,0.5"])
    m = read_measurements(path, dof=3, joint_limits=long, joint_types=TYPES)
    assert m.q[:, 0].tolist() == [7.5, -6.5]
    # the revolute columns still are
    with pytest.raises(MeasurementFileError, match="look like degrees"):
        read_measurements(write(tmp_path, ["0.5,30.0,-0.2,1.5,0.25,0.75"]), dof=3, joint_limits=long, joint_types=TYPES)


def test_prismatic_limits_are_metres_in_the_message(tmp_path):
    path = write(tmp_path, ["500.0,0.1,-0.2,1500.0,250.0,750.0", "1200.0,0.3,0.2,1250.0,-500.0,500.0"])
    with pytest.raises(MeasurementFileError) as info:
        read(path, length_unit="mm")
    assert info.value.line == 3 and info.value.column == "q1"
    assert "q1 = 1200 mm (1.2 m) is outside the limits" in str(info.value) and "[-1, 1] m" in str(info.value)
