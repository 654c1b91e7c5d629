"""What a new user meets first: the version, the help texts, the names of the data's environment variable."""

import re
from pathlib import Path

import pytest
import torch
import yaml

import torchcal
from torchcal import __version__
from torchcal.cli import main

TESTS = Path(__file__).resolve().parents[1]


def test_version_prints_the_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"torchcal {__version__}"


def test_the_tests_name_the_real_data_by_one_environment_variable():
    """Each data set the tests read is found through one variable, whatever test reads it."""
    names = set()
    for path in TESTS.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        for var, rest in re.findall(r"environ\.get\(\s*\"(TORCHCAL_[A-Z0-9_]+)\",([^\n]*\n[^\n]*)", text):
            if "ur10-ipa" in rest:
                names.add(var)
    assert names == {"TORCHCAL_IPA_DATA"}


def _help(*command: str) -> str:
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), pytest.raises(SystemExit):
        main([*command, "--help"])
    return " ".join(buf.getvalue().split())  # argparse wraps at the terminal width


def test_help_texts_say_what_the_commands_do(monkeypatch):
    monkeypatch.setenv("COLUMNS", "2000")  # no wrapping: argparse breaks long words at the terminal width
    top = _help()
    assert "the K that best serve the calibration method" in top and "for a kinematic calibration" not in top
    cal = _help("calibrate")
    assert "named effects (joint compliance, backlash, cyclic joint errors, transmission, drift)" in cal
    assert "[,rx,ry,rz[,srx,sry,srz]][,station][,probe]" in cal
    assert "run directory to write; an existing one" in cal and "output directory" not in cal
    assert "run directory to write; an existing one" in _help("station")
    assert "coupling (:J<-K" in _help("simulate")
    assert "trust columns sx,sy,sz [m] and extrapolation" in _help("predict")


def test_export_under_a_name_robot_cannot_load_says_so(run_dir, tmp_path, capsys):
    """``--robot`` tells a description's kind by its ending: a DH table written as ``cal.dh`` is written, and the
    command says how to load it back (a file ending in .yaml is not told)."""
    assert main(["export", str(run_dir), "--format", "dh", "--out", str(tmp_path / "cal.dh")]) == 0
    err = capsys.readouterr().err
    assert "rename" in err and ".yaml or .yml" in err and (tmp_path / "cal.dh").exists()
    assert main(["export", str(run_dir), "--format", "dh", "--out", str(tmp_path / "cal.yaml")]) == 0
    assert "rename" not in capsys.readouterr().err


def test_export_writes_what_other_software_reads(run_dir, tmp_path):
    """A calibrated run exported for the UR ROS 2 driver and as a DH table, each refused where it cannot hold
    the robot, nothing written then."""
    from torchcal.use.rundir import load_model

    robot = load_model(run_dir)[0].robot
    q = torch.rand(200, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 4 - 2
    assert main(["export", str(run_dir), "--format", "dh", "--out", str(tmp_path / "cal.yaml"), "--quiet"]) == 0
    back = torchcal.load_robot(tmp_path / "cal.yaml")
    assert float((back(q) - robot(q)).detach().abs().max()) < 1e-9
    assert main(["export", str(run_dir), "--format", "ur-ros2", "--out", str(tmp_path / "ur.yaml"), "--quiet"]) == 0
    doc = yaml.safe_load((tmp_path / "ur.yaml").read_text())
    assert doc["kinematics"]["shoulder"].keys() == {"x", "y", "z", "roll", "pitch", "yaw"}
    # the same file again: torchcal wrote it, it is replaced without --force
    assert main(["export", str(run_dir), "--format", "ur-ros2", "--out", str(tmp_path / "ur.yaml"), "--quiet"]) == 0
    assert main(["export", str(run_dir), "--format", "urdf", "--out", str(tmp_path / "cal.urdf"), "--quiet"]) == 0
    assert "<robot" in (tmp_path / "cal.urdf").read_text()
    urdf_run = tmp_path / "not-a-run"
    urdf_run.mkdir()
    assert main(["export", str(urdf_run), "--format", "dh", "--out", str(tmp_path / "x.yaml"), "--quiet"]) == 2
    assert not (tmp_path / "x.yaml").exists()


def _on_a_terminal(args: list[str], cwd) -> str:
    """Run ``python -m torchcal ARGS`` with stdout and stderr on a pseudo-terminal; what it printed there."""
    import fcntl
    import os
    import pty
    import struct
    import subprocess
    import sys
    import termios

    master, slave = pty.openpty()
    # a terminal of 30 x 120 (a fresh pseudo-terminal is 0 x 0, where tqdm draws an empty bar)
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 120, 0, 0))
    env = {**os.environ, "PYTHONPATH": str(TESTS.parent), "OMP_NUM_THREADS": "1", "COLUMNS": "120"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "torchcal", *args],
        stdout=slave,
        stderr=slave,
        stdin=subprocess.DEVNULL,
        cwd=cwd,
        env=env,
    )
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    os.close(master)
    assert proc.wait(timeout=120) == 0
    return b"".join(chunks).decode("utf-8", "replace")


@pytest.mark.slow
def test_a_long_step_shows_progress_on_a_terminal_and_nothing_with_quiet(tmp_path):
    args = ["plan", "--robot", "ur5", "--n", "40", "--pool", "300", "--out"]
    shown = _on_a_terminal([*args, str(tmp_path / "a.csv")], tmp_path)
    assert "plan: picks:" in shown and "%|" in shown  # tqdm's bar, drawn on the terminal
    assert _on_a_terminal([*args, str(tmp_path / "b.csv"), "--quiet"], tmp_path) == ""
