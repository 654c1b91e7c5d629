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
