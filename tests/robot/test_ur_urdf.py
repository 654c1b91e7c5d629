"""torchcal.robot.ur_urdf (behind scripts/make_ur_urdf.py): the shipped UR URDFs are what it generates from the
YAMLs, and their chains reproduce the DH tables."""

from pathlib import Path

import pytest

from torchcal.errors import RobotSpecError
from torchcal.robot.ur_urdf import MODELS, TOLERANCE, check_numerics, load_table, render

ROBOTS = Path(__file__).resolve().parents[2] / "robots"


@pytest.mark.parametrize("name", MODELS)
def test_shipped_urdf_is_generated_and_matches_the_dh_table(name):
    model = load_table(ROBOTS / f"{name}.yaml")
    text = render(model, f"robots/{name}.yaml")
    path = ROBOTS / f"{name}.urdf"
    assert path.read_text(encoding="utf-8") == text
    worst = check_numerics(model, text, path, n=5)
    assert {"urdf", "base", "com"} <= set(worst)
    for key, err in worst.items():
        assert err < TOLERANCE.get(key, 1e-12), key


def test_a_table_off_urs_pattern_is_refused(tmp_path):
    text = (ROBOTS / "ur5.yaml").read_text(encoding="utf-8")
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("convention: standard", "convention: modified"), encoding="utf-8")
    with pytest.raises(RobotSpecError, match="standard DH"):
        load_table(bad)
