"""Hostile inputs, round 5 (issue 47): the simulator's own output at joint limits, devices and FIFOs given as any path,
``convert``'s silent wrong results, misleading messages and the layouts the importer could not express.

Every case is a clear refusal (exit 2, naming the file, line, column or option, nothing written) or a correct
result; never exit 1, never a hang.
"""

import math

import pytest
import torch
from _cli import cli_simulate, deadline, refused, snapshot

from torchcal.cli import main
from torchcal.data.measurements import MeasurementFileError, read_measurements
from torchcal.robot.load import load_robot


def run_cli(argv, seconds=60) -> int:
    """The command's exit status (argparse's refusals too), within ``seconds``."""
    with deadline(seconds):
        try:
            return main([*argv, "--quiet"])
        except SystemExit as e:
            return e.code


def refuse(capsys, tmp_path, argv, *needles, seconds=60):
    """``argv`` exits 2 naming every needle, and ``tmp_path`` is as it was."""
    before = snapshot(tmp_path)
    assert run_cli(argv, seconds) == 2
    err = refused(capsys, *needles)
    assert snapshot(tmp_path) == before
    return err


# ------------------------------------------------------------------------------- 1: the simulator at joint limits


def test_simulated_panda_at_its_limits_is_read_back(tmp_path):
    """Issue 47 item 1: joint noise put line 93's q2 3.9e-6 rad past panda's limit, and calibrate refused it."""
    assert cli_simulate(tmp_path / "s", "--seed", "13", "--poses", "150", "--test-poses", "20", robot="panda") == 0
    robot = load_robot("panda")
    for part in ("train.csv", "test.csv"):
        m = read_measurements(tmp_path / "s" / part, dof=robot.dof, joint_limits=robot.limits, robot_name="panda")
        assert bool((m.q >= robot.limits[:, 0]).all() and (m.q <= robot.limits[:, 1]).all())


def test_a_limit_message_shows_the_excess(tmp_path):
    """A reading 3.9e-6 rad past a limit printed with six digits looked equal to the limit."""
    robot = load_robot("panda")
    lo = robot.limits[1, 0].item()
    q = [0.0, lo - 3.9e-6, 0.0, -1.5, 0.0, 1.5, 0.0]
    (tmp_path / "d.csv").write_text("q1,q2,q3,q4,q5,q6,q7,x,y,z\n" + ",".join(map(repr, q)) + ",1,0,0\n")
    with pytest.raises(MeasurementFileError) as info:
        read_measurements(tmp_path / "d.csv", dof=7, joint_limits=robot.limits, robot_name="panda")
    msg = str(info.value)
    assert f"{lo - 3.9e-6:.12g}" in msg and "3.9e-06 rad below" in msg, msg


def test_a_limit_message_in_degrees_shows_the_excess_in_both(tmp_path):
    robot = load_robot("panda")
    hi = robot.limits[0, 1].item()
    q = [hi + 1e-5, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0]
    row = ",".join(repr(math.degrees(v)) for v in q)
    (tmp_path / "d.csv").write_text("q1,q2,q3,q4,q5,q6,q7,x,y,z\n" + row + ",1,0,0\n")
    with pytest.raises(MeasurementFileError) as info:
        read_measurements(tmp_path / "d.csv", dof=7, joint_limits=robot.limits, robot_name="panda", angle_unit="deg")
    assert "1e-05 rad) above" in str(info.value) and "0.000573 deg" in str(info.value), str(info.value)


def _unused():  # keep imports used while the module grows
    return torch, refuse
