"""The paper reproductions (scripts/reproduce_table1.py, reproduce_table2.py) in --quick mode: files, the last-line
JSON, known answers of the absorbed parameters and the findings of Horvath & Neuner (2024), Sec. 2.2.2-2.2.3."""

import contextlib
import importlib.util
import io
import json
import sys
from pathlib import Path

import pytest
import torch

import torchcal
from experiments import table1 as t1
from experiments import table2 as t2

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def load_script(name):
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def run_script(name, out):
    """``main(["--quick", "--json", "--out", out])``; the parsed last stdout line and the whole stdout."""
    stdout = io.StringIO()
    threads = torch.get_num_threads()
    with contextlib.redirect_stdout(stdout):
        assert load_script(name).main(["--quick", "--json", "--out", str(out)]) == 0
    assert torch.get_num_threads() == threads  # --threads is restored for the rest of the session
    return json.loads(stdout.getvalue().strip().splitlines()[-1]), stdout.getvalue()


@pytest.fixture(scope="module")
def table1(tmp_path_factory):
    out = tmp_path_factory.mktemp("table1")
    result, stdout = run_script("reproduce_table1", out)
    return result, out, stdout


@pytest.fixture(scope="module")
def table2(tmp_path_factory):
    out = tmp_path_factory.mktemp("table2")
    result, stdout = run_script("reproduce_table2", out)
    return result, out, stdout


def test_table1_json_line_and_files(table1):
    result, out, stdout = table1
    assert result == json.loads((out / "table1.json").read_text())
    assert result["config"]["draws"] == 5 and result["config"]["poses"] == 150
    assert list(result["rows"]) == [*t1.PARAMETERS, "all"]
    assert stdout.splitlines()[0].split()[:4] == ["par", "tx", "ty", "tz"]  # the printed table comes first
    md = (out / "table1.md").read_text()
    assert "| theta1 |" in md and "/ 36 |" in md  # the paper's theta1 -> rz next to ours
    assert (out / "fig5.png").stat().st_size > 10_000


def test_table1_absorbed_parameters_leave_nothing_the_others_a_lot(table1):
    rows = table1[0]["rows"]
    for name in t1.ABSORBED:
        # the bias does move the probe (theta6 least: it only turns the lever arm about the flange axis)
        assert rows[name]["nominal_mm"] > 1e-4, name
        assert rows[name]["remaining_mm"] < 0.01 * rows[name]["nominal_mm"], name
    for name in ("a2", "d5", "theta2", "alpha2"):
        assert rows[name]["remaining_mm"] > 0.2 * rows[name]["nominal_mm"], name
    assert set(table1[0]["summary"]["absorbed_ours"]) == set(t1.ABSORBED)
    # more than one parameter biased at once: the fit cannot absorb the remaining ones
    assert rows["all"]["remaining_mm"] > 0.5 * rows["all"]["nominal_mm"]


def test_table1_known_answers_of_the_absorbed_parameters(table1):
    """d1 shifts the base along z, theta1 turns it about z, a6 / d6 shift the flange along x / z: the fit takes
    each bias exactly into one component, so its mean |deviation| is the mean |bias|."""
    rows = table1[0]["rows"]
    for name, component in (("d1", "tz"), ("theta1", "rz"), ("a6", "lever_x"), ("d6", "lever_z")):
        assert rows[name]["mean_abs"][component] == pytest.approx(rows[name]["mean_abs_bias"], rel=1e-6), name
    assert rows["d1"]["mean_abs"]["tx"] < 1e-6 and rows["a6"]["mean_abs"]["tz"] < 1e-6


def test_table2_json_line_and_files(table2):
    result, out, _ = table2
    assert result == json.loads((out / "table2.json").read_text())
    assert result["config"]["draws"] == 3 and result["config"]["poses"] == 150
    assert list(result["rows"]) == ["remaining", "absorbed", "all"]
    assert "| absorbed |" in (out / "table2.md").read_text()


def test_table2_remaining_biases_are_recovered_absorbed_ones_are_not(table2):
    result = table2[0]
    assert set(result["fixed_parameters"]) == set(t2.PAPER_FIXED)
    assert set(result["lm_status"]) == {"converged"}
    rows = result["rows"]
    rem, absorbed, everything = rows["remaining"], rows["absorbed"], rows["all"]
    # noise-free: the calibration recovers the transformation and lever arm (mm, arcsec)
    for c in t2.COMPONENTS:
        assert rem["max_abs"][c] < 1e-3, c
    # ... while the PCM fit of the same draws is clearly off
    assert rem["heldout_rmse_pcm_mm"] > 0.05
    # the fixed parameters' biases land in the transformation and lever arm
    for c in ("tz", "lever_x", "lever_z"):
        assert absorbed["mean_abs"][c] > 0.01, c
    # and the 'all' variant ends where 'absorbed' does (paper: "the same mean deviations")
    for c in t2.COMPONENTS:
        assert everything["mean_abs"][c] == pytest.approx(absorbed["mean_abs"][c], abs=1e-4), c
    # every variant fits the held-out poses to round-off: the bias only moved into other parameters
    for row in rows.values():
        assert row["heldout_rmse_mm"] < 1e-6


def test_single_posture_keeps_the_tracker_and_one_shoulder_configuration():
    any_, single = t1.make_setup(60, 10, 3, "any"), t1.make_setup(60, 10, 3, "single")
    assert torch.equal(any_.T_tracker_base, single.T_tracker_base)
    assert torch.equal(any_.t_flange_probe, single.t_flange_probe)
    assert single.q.shape == (60, 6) and single.q_test.shape == (10, 6)
    q = torch.cat([single.q, single.q_test])
    with torch.no_grad():
        T = torchcal.load_robot("ur5")(q)
    assert bool(t1._single_posture(T, q, single.t_flange_probe).all())
    with torch.no_grad():
        mixed = t1._single_posture(torchcal.load_robot("ur5")(any_.q), any_.q, any_.t_flange_probe)
    assert 0 < int(mixed.sum()) < len(mixed)  # the default mixes both configurations
