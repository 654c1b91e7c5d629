"""report.json unchanged for the same seed: a fresh small run against the stored golden report.

The golden reports and the code that regenerates them are in ``tests/golden/`` (see its module
docstring). Numbers compare to 1e-9 relative (absolute 1e-12 m or rad or mm for values at zero, where
a relative test means nothing); strings, booleans, None and the structure (keys, list lengths) compare
exactly. Skipped keys: none so far (:data:`VOLATILE`; the report holds no timings and its one path,
``robot_spec``, is the built-in name ``ur5`` here).
"""

import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent / "golden"))
import golden  # noqa: E402

#: report keys whose values may differ between runs (timings, absolute paths), at any depth
VOLATILE: frozenset[str] = frozenset()
REL, ABS = 1e-9, 1e-12


def differences(expected, got, where: str = "report") -> list[str]:
    """Every place where ``got`` differs from ``expected`` (empty when they agree)."""
    if isinstance(expected, dict):
        if not isinstance(got, dict):
            return [f"{where}: expected an object, got {type(got).__name__}"]
        out = (
            [f"{where}: keys {sorted(set(expected) ^ set(got))} in only one of the two"]
            if set(expected) != set(got)
            else []
        )
        for k in expected:
            if k in got and k not in VOLATILE:
                out += differences(expected[k], got[k], f"{where}.{k}")
        return out
    if isinstance(expected, list):
        if not isinstance(got, list) or len(got) != len(expected):
            return [f"{where}: expected a list of {len(expected)}, got {got!r:.200}"]
        return [d for i, (a, b) in enumerate(zip(expected, got)) for d in differences(a, b, f"{where}[{i}]")]
    if isinstance(expected, float) or (
        isinstance(expected, int) and not isinstance(expected, bool) and isinstance(got, float)
    ):
        if (
            isinstance(got, bool)
            or not isinstance(got, int | float)
            or not math.isclose(expected, got, rel_tol=REL, abs_tol=ABS)
        ):
            return [f"{where}: expected {expected!r}, got {got!r}"]
        return []
    return [] if expected == got and type(expected) is type(got) else [f"{where}: expected {expected!r}, got {got!r}"]


def test_differences_finds_a_changed_number_and_a_missing_key():
    a = {"x": 1.0, "y": [1, "a", {"z": None}]}
    assert differences(a, json.loads(json.dumps(a))) == []
    assert differences(a, {"x": 1.0 + 1e-6, "y": [1, "a", {"z": None}]}) == ["report.x: expected 1.0, got 1.000001"]
    assert len(differences(a, {"x": 1.0, "y": [1, "a", {}]})) == 1


@pytest.mark.slow
@pytest.mark.parametrize("method", list(golden.CASES))
def test_report_matches_the_golden_report(method):
    expected = json.loads(golden.path(method).read_text(encoding="utf-8"))
    got = golden.golden_report(method)
    diff = differences(expected, got)
    assert not diff, f"{len(diff)} differences from {golden.path(method).name}:\n" + "\n".join(diff[:30])


@pytest.mark.slow
def test_a_loaded_robot_gives_the_same_report_as_its_name():
    from torchcal._threads import torch_threads
    from torchcal.pipeline import Options, calibrate
    from torchcal.report import build_report
    from torchcal.robot import load_robot
    from torchcal.sim import SimConfig, simulate

    with torch_threads(1):
        c = simulate(SimConfig(robot="ur5", poses=120, test_poses=10, seed=3))
        by_name = build_report(calibrate("ur5", c.train, Options(method="kinematic", seed=3)))
        robot = load_robot("ur5")
        run = calibrate(robot, c.train, Options(method="kinematic", seed=3))
    assert run.robot is robot and run.robot_spec == robot.source
    got = json.loads(json.dumps(build_report(run)))
    assert got.pop("robot_spec") == str(robot.source) and by_name.pop("robot_spec") == "ur5"
    assert differences(json.loads(json.dumps(by_name)), got) == []
