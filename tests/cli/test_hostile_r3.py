"""Hostile inputs, round 3 (issue 34 items 7-9, issue 35): vendor robot files, noise-level warnings and ``--quiet``,
orientation rows in the gross-error screening, and the internal errors and silent wrong results of issue 35 (items
1, 4-7, 10, 11; 2, 3 and 8 are ``plan``'s, 9 and the ``station`` parts of 11 ``station``'s).

Every case is a clear refusal (exit 2, naming the file, row, column or parameter, nothing written) or a correct
result; never exit 1, never a hang. Campaigns are tiny and module-scoped.
"""


import pytest
import test_hostile as hostile
from _cli import cli_simulate, deadline

import torchcal

write = hostile.write


def refused(capsys, *needles: str) -> str:
    """The command's stderr: an error holding every needle, no traceback, no internal error."""
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err and "this is a bug" not in err, err
    for n in needles:
        assert n in err, (n, err)
    return err


# ------------------------------------------------------- issue 34 item 7: a mimic whose source is off the chain

VENDOR_COLUMN = """<?xml version="1.0"?>
<robot name="vendor_column">
  <link name="base"/><link name="virtual"/><link name="seg1"/><link name="seg2"/><link name="arm"/><link name="flange"/>
  <joint name="column_prismatic_joint" type="prismatic">
    <parent link="base"/><child link="virtual"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.6" effort="0" velocity="0"/>
  </joint>
  <joint name="column_lower_joint" type="prismatic">
    <parent link="base"/><child link="seg1"/><origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.3" effort="0" velocity="0"/>
    <mimic joint="column_prismatic_joint" multiplier="0.5" offset="0"/>
  </joint>
  <joint name="column_middle_joint" type="prismatic">
    <parent link="seg1"/><child link="seg2"/><origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.3" effort="0" velocity="0"/>
    <mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.01"/>
  </joint>
  <joint name="pan" type="revolute">
    <parent link="seg2"/><child link="arm"/><origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="0" velocity="0"/>
  </joint>
  <joint name="tilt" type="revolute">
    <parent link="arm"/><child link="flange"/><origin xyz="0.5 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="0" velocity="0"/>
  </joint>
</robot>
"""


def test_a_mimic_source_on_a_side_branch_becomes_a_reading(tmp_path):
    robot = torchcal.load_robot(write(tmp_path / "column.urdf", VENDOR_COLUMN))
    assert robot.joint_names == ["column_lower_joint", "column_middle_joint", "pan", "tilt"]
    assert robot.reading_names == ["column_prismatic_joint", "pan", "tilt"] and robot.dof == 3
    A = robot.readings.matrix().detach()
    assert A[:, 0].tolist() == [0.5, 0.5, 0.0, 0.0] and robot.readings.offset.tolist() == [0.0, 0.01, 0.0, 0.0]
    # the column's reading takes the range its segments allow: 0.3 m each at half the reading
    assert robot.limits[0].tolist() == pytest.approx([0.0, 0.6])
    with deadline(120):
        assert (
            cli_simulate(tmp_path / "s", "--poses", "20", "--test-poses", "5", robot=str(tmp_path / "column.urdf")) == 0
        )


def test_a_mimic_of_nothing_is_still_refused(tmp_path):
    text = VENDOR_COLUMN.replace(
        'mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.01"', 'mimic joint="lift"'
    )
    with pytest.raises(torchcal.RobotSpecError, match="mimics joint 'lift', which is not a movable joint"):
        torchcal.load_robot(write(tmp_path / "column.urdf", text))
