"""torchcal.use.export: the command's formats are the module's, and an unknown one is refused before anything is
read or written."""

import pytest

from torchcal.cli import build_parser
from torchcal.use.export import FORMATS, export_run


def test_the_command_offers_the_formats_export_writes():
    (sub,) = [a for a in build_parser()._actions if a.dest == "command"]
    (fmt,) = [a for a in sub.choices["export"]._actions if a.dest == "format"]
    assert tuple(fmt.choices) == FORMATS


def test_an_unknown_format_is_refused_before_the_run_is_read(tmp_path):
    with pytest.raises(ValueError, match="ur-ros2, dh, urdf"):
        export_run(tmp_path / "no-such-run", "step", tmp_path / "out" / "robot.step")
    assert not (tmp_path / "out").exists()
