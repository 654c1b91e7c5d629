"""scripts/few_rows_sigma.py and scripts/export_as_robot.py (issue 46 items 3 and 6) run, print JSON and refuse what
they cannot measure."""

import subprocess
import sys

import pytest
from _cli import ROOT, cli_simulate, run_script


@pytest.mark.slow
def test_few_rows_sigma_covers_fresh_rows_of_a_parallelogram_arm():
    res, _ = run_script("few_rows_sigma.py", "--robots", "fanuc_like", "--seeds", "1", "--test-poses", "60", "--json")
    (case,) = res["cases"]
    assert case["n_holdout"] == 8 and case["few_rows_scale"] >= 1.0
    assert case["within_3sigma"] >= 0.95 and case["median_ratio"] >= 0.3, case


@pytest.mark.slow
def test_a_runs_own_export_as_robot_keeps_its_sigma(tmp_path):
    assert cli_simulate(tmp_path / "c", "--poses", "80", "--test-poses", "40", "--seed", "2") == 0
    res, _ = run_script("export_as_robot.py", str(tmp_path / "c"), "--method", "kinematic", "--json")
    (c,) = res["campaigns"]
    first, again = c["first"], c["again"]["dh"]
    assert again["rmse_mm"] == pytest.approx(first["rmse_mm"], rel=1e-3)
    assert again["median_ratio"] == pytest.approx(first["median_ratio"], rel=0.05)
    assert again["within_3sigma"] >= first["within_3sigma"] - 0.03


@pytest.mark.parametrize(
    "script, args, words",
    [
        ("few_rows_sigma.py", ["--robots", "ur7"], "--robots must name some of"),
        ("export_as_robot.py", ["."], "expected a folder with train.csv and test.csv"),
        ("export_as_robot.py", ["--formats", "ros"], "the following arguments are required"),
    ],
)
def test_the_scripts_refuse_what_they_cannot_measure(script, args, words):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / script), *args], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert proc.returncode == 2 and words in proc.stderr, proc.stderr[-500:]
