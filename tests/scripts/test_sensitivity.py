"""scripts/sensitivity.py (Horvath & Neuner 2024, Sec. 3.3, Fig. 13) in --quick mode: the last-line JSON, the
files, the exactness of the batched draws, and the paper's findings that do not depend on the trajectory."""

import contextlib
import importlib.util
import io
import json
import sys
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "sensitivity.py"


def load():
    if "sensitivity" not in sys.modules:
        spec = importlib.util.spec_from_file_location("sensitivity", SCRIPT)
        module = importlib.util.module_from_spec(spec)
        sys.modules["sensitivity"] = module
        spec.loader.exec_module(module)
    return sys.modules["sensitivity"]


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("sensitivity")
    stdout = io.StringIO()
    threads = torch.get_num_threads()
    with contextlib.redirect_stdout(stdout):
        assert load().main(["--quick", "--json", "--out", str(out)]) == 0
    assert torch.get_num_threads() == threads
    return json.loads(stdout.getvalue().strip().splitlines()[-1]), out, stdout.getvalue()


@pytest.mark.slow
def test_json_line_files_and_table(quick):
    result, out, stdout = quick
    assert result == json.loads((out / "sensitivity.json").read_text())
    assert (out / "fig13_sensitivity.png").stat().st_size > 10_000
    assert stdout.splitlines()[0].split()[0] == "parameter"
    par = result["parameters"]
    # term: the identifiable DH set (the paper's fixed ones are out), the instrument's 6, the lever arm's 3
    assert [n for n in par if not n.startswith(("instrument.", "tool."))][:3] == ["a1", "alpha1", "a2"]
    for fixed in ("d1", "d3", "d4", "d6", "theta1", "theta6", "alpha6", "a6"):
        assert fixed not in par
    assert [n for n in par if n.startswith("instrument.")] == [
        f"instrument.{c}" for c in ("tx", "ty", "tz", "rx", "ry", "rz")
    ]
    assert [n for n in par if n.startswith("tool.")] == ["tool.x", "tool.y", "tool.z"]
    assert result["filter_status"] == ["ok"]
    for p in par.values():
        assert {"mean_dG_mm", "max_dG_mm", "train_mean_dG_mm", "test_mean_dG_mm"} <= set(p)


def test_batched_draws_equal_a_direct_run_of_the_biased_model(quick):
    """A biased instrument rotation carried by the draw's kinematics and rotated output layer is the same filter
    as the biased model run on its own (an equivalent-paths check, to round-off)."""
    assert quick[0]["check_max_abs_diff_m"] < 1e-12


def test_instrument_translation_cancels_rotation_and_lever_arm_do_not(quick):
    par = quick[0]["parameters"]
    for c in ("tx", "ty", "tz"):  # the relative formulation (Eq. 14) cancels T_tracker_base's translation
        assert par[f"instrument.{c}"]["max_dG_mm"] < 1e-9
    for c in ("rx", "ry", "rz"):  # its rotation turns the kinematic increments
        assert par[f"instrument.{c}"]["mean_dG_mm"] > 0.005
    for c in ("x", "y"):  # lever arm x, y act directly on the geometry
        assert par[f"tool.{c}"]["mean_dG_mm"] > 0.01
    # every identifiable DH parameter leaves a visible trace: all are estimable in principle (Sec. 3.3)
    assert min(p["mean_dG_mm"] for p in par.values() if p["group"] == "dh") > 1e-3
