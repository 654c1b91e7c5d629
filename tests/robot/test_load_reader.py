"""``load_urdf(reader="elements")`` reads the same numbers as yourdfpy, without importing it."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchcal.errors import OptionError, RobotSpecError
from torchcal.robot import load_robot, load_urdf, write_urdf
from torchcal.robot.load import ROBOTS_DIR

HERE = Path(__file__).resolve().parent
URDFS = sorted(ROBOTS_DIR.glob("*.urdf")) + [
    HERE / "data" / "kinova_like.urdf",
    HERE.parent / "estimate" / "data" / "gen3_rounded.urdf",
]


def _same(a, b) -> list[str]:
    """What differs between two loaded robots (empty: bit for bit the same)."""
    out = [k for k in ("name", "joint_names", "link_names", "base_link", "tip_link") if getattr(a, k) != getattr(b, k)]
    sa, sb = a.state_dict(), b.state_dict()
    if sa.keys() != sb.keys():
        return out + ["state keys"]
    out += [k for k in sa if not torch.equal(sa[k], sb[k])]
    for k in ("masses", "coms", "limits"):
        x, y = getattr(a, k), getattr(b, k)
        if (x is None) != (y is None) or (x is not None and not torch.equal(x, y)):
            out.append(k)
    return out


@pytest.mark.parametrize("path", URDFS, ids=lambda p: p.name)
def test_elements_reader_equals_yourdfpy_bit_for_bit(path):
    assert path.is_file()
    assert _same(load_urdf(path), load_urdf(path, reader="elements")) == []


def test_elements_reader_on_a_calibrated_urdf(tmp_path):
    robot = load_robot("ur10")
    with torch.no_grad():  # a geometry off the nominal one, with non-trivial rpy in every origin
        robot.geometry.delta.copy_(
            torch.linspace(-1e-3, 1e-3, robot.geometry.delta.numel()).reshape_as(robot.geometry.delta)
        )
        robot.tool.nominal.copy_(torch.tensor([0.01, -0.02, 0.1], dtype=torch.float64))
    path = tmp_path / "cal.urdf"
    write_urdf(robot, path)
    for tip in (None, "probe"):
        a, b = load_urdf(path, tip_link=tip), load_urdf(path, tip_link=tip, reader="elements")
        assert _same(a, b) == []
        q = torch.linspace(-1, 1, 6 * 5, dtype=torch.float64).reshape(5, 6)
        assert torch.equal(a(q), b(q))


def test_elements_reader_errors(tmp_path):
    bad = tmp_path / "bad.urdf"
    bad.write_text(
        '<robot name="r"><link name="a"/><link name="b"/>'
        '<joint name="j" type="revolute"><parent link="a"/></joint></robot>'
    )
    with pytest.raises(RobotSpecError, match="bad.urdf: joint 'j' has no <child link"):
        load_urdf(bad, reader="elements")
    with pytest.raises(OptionError, match="reader must be"):
        load_urdf(URDFS[0], reader="lxml")


def test_elements_reader_does_not_import_yourdfpy():
    code = (
        "import sys; from torchcal.robot import load_robot; "
        f"r = load_robot({str(URDFS[0])!r}, reader='elements'); "
        "print(sorted(m for m in ('yourdfpy', 'trimesh', 'scipy', 'networkx', 'lxml') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == "[]"


def test_elements_reader_refuses_what_the_strict_parser_refuses(tmp_path):
    doctype = tmp_path / "doctype.urdf"
    doctype.write_text(
        '<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY x "1">]>\n<robot name="r"><link name="a"/></robot>'
    )
    truncated = tmp_path / "truncated.urdf"
    truncated.write_text('<robot name="r"><link name="a"/><joint name="j" type="fixed">')
    for reader in ("yourdfpy", "elements"):
        with pytest.raises(RobotSpecError, match="DOCTYPE/entity declaration is not accepted"):
            load_urdf(doctype, reader=reader)
        with pytest.raises(RobotSpecError, match="truncated.urdf: not well-formed XML"):
            load_urdf(truncated, reader=reader)
