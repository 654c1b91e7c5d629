"""What several test files share about the command line: ``simulate`` into a folder, the fields CONTRACT §4
requires of the ``report.json`` that ``calibrate`` writes, a script of ``scripts/`` run for its JSON line, and the
hostile-input tests' helpers and fixtures (a small campaign, a kinematic run of it, a deadline, a snapshot)."""

import json
import signal
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

import pytest

from torchcal.cli import main

#: the fields every report.json holds at least (CONTRACT §4)
REPORT_FIELDS = (
    "robot",
    "method",
    "n_train",
    "n_holdout",
    "rmse_before_mm",
    "rmse_geometric_mm",
    "rmse_after_mm",
    "max_after_mm",
    "global_test",
    "effects",
    "parameters",
)


def cli_simulate(out: Path | str, *options: str, robot: str = "ur5") -> int:
    """``torchcal simulate --robot ROBOT --out OUT OPTIONS... --quiet`` through :func:`torchcal.cli.main`.

    Returns:
        The command's exit status.
    """
    return main(["simulate", "--robot", robot, "--out", str(out), *options, "--quiet"])


ROOT = Path(__file__).resolve().parents[1]


def run_script(name: str, *args: str, timeout: float = 300) -> tuple[dict, str]:
    """``python scripts/NAME ARGS...`` from the repository root in a fresh process; it must exit 0.

    Returns:
        The JSON object of its last stdout line, and its stderr.
    """
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / name), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


def _golden():
    here = str(ROOT / "tests" / "golden")
    if here not in sys.path:
        sys.path.insert(0, here)
    import golden

    return golden


def golden_campaign():
    """The golden reports' simulated campaign (``tests/golden/golden.py``: 200 UR5 poses, a joint-2 compliance the
    loop names and a smooth field the learned stage takes), simulated afresh."""
    return _golden().campaign()


def golden_auto_run():
    """The golden report's ``auto`` run (seed 7) of :func:`golden_campaign`, fitted once per test process and
    shared: do not change it (``copy.deepcopy`` first)."""
    return _golden().golden_run("auto")


# ------------------------------------------------------------------ hostile inputs (tests/cli/test_hostile*.py)


class DeadlineExceeded(BaseException):
    """Raised by :func:`deadline`. Not a ``TimeoutError``: that is an ``OSError``, which the code under test may
    catch (reading a FIFO that blocks, then 'cannot read' the file), and the hang would pass as a refusal."""


def refused(capsys, *needles) -> str:
    """The command's stderr: an error holding every needle (as text), no traceback, no internal error."""
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err and "this is a bug" not in err, err
    for n in needles:
        assert str(n) in err, (n, err)
    return err


@contextmanager
def deadline(seconds: int):
    """Fail instead of hanging (a cycle that loops forever would otherwise stall the suite)."""

    def boom(*_):
        raise DeadlineExceeded(f"took more than {seconds} s")

    old = signal.signal(signal.SIGALRM, boom)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def snapshot(root: Path) -> dict:
    """Every path under ``root`` with its bytes (files) or None (directories)."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def run_cli(argv, seconds=60) -> int:
    """The command's exit status (argparse's refusals too), within ``seconds``."""
    with deadline(seconds):
        try:
            return main([*argv, "--quiet"])
        except SystemExit as e:
            return e.code


def refuse(capsys, tmp_path, argv, *needles, seconds=60):
    """``argv`` exits 2 naming every needle, and ``tmp_path`` is as it was; returns what it printed on stderr."""
    before = snapshot(tmp_path)
    assert run_cli(argv, seconds) == 2
    err = refused(capsys, *needles)
    assert snapshot(tmp_path) == before
    return err


# session-scoped: seven modules of tests/cli read the same campaign and run (they copy a run before changing it), and
# computing them once per test process instead of once per module saves a simulation and a calibration per module
@pytest.fixture(scope="session")
def campaign(tmp_path_factory):
    root = tmp_path_factory.mktemp("campaign")
    assert cli_simulate(root / "sim", "--poses", "100", "--test-poses", "20", "--seed", "4") == 0
    return root / "sim"


@pytest.fixture(scope="session")
def run_dir(campaign, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "cal"
    assert calibrate(campaign / "train.csv", out) == 0
    return out


def calibrate(data, out, *extra):
    return main(
        ["calibrate", str(data), "--robot", "ur5", "--method", "kinematic", "--out", str(out), "--quiet", *extra]
    )
