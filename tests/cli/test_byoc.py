"""What a new user meets first: the version, the help texts, the names of the data's environment variable."""

import re
from pathlib import Path

import pytest

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
