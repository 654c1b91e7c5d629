"""Where a calibration's time goes (``scripts/profile_calibration.py``): the stages through the memory probe, the
kernels and the torchcal functions through cProfile of every thread, on a small kinematic run."""

import subprocess
import sys

import pytest

from experiments.profile_calibration import KERNELS, _code_key, profile


def test_every_kernel_names_a_function_that_exists():
    for label, targets in KERNELS.items():
        for t in targets:
            path, line, name = _code_key(t)
            assert path.endswith(".py") and line > 0 and name == t.rsplit(".", 1)[-1].rsplit(":", 1)[-1], label


def test_a_missing_function_is_an_error():
    with pytest.raises(KeyError, match="no nested function nothing"):
        _code_key("torchcal.estimate.problem:orientation_function.nothing")


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    out = tmp_path_factory.mktemp("prof") / "sim"
    argv = ["simulate", "--robot", "ur5", "--poses", "120", "--test-poses", "10", "--out", str(out), "--quiet"]
    subprocess.run([sys.executable, "-m", "torchcal", *argv], check=True)
    return out / "train.csv"


@pytest.mark.slow
def test_the_profile_names_the_stages_the_kernels_and_the_costly_functions(campaign, tmp_path):
    res = profile(str(campaign), "ur5", "kinematic", tmp_path)
    assert [s["stage"] for s in res["stages"]] == ["import", "robot", "read", "fit", "report"]
    # the report's own stages are timed too: its trust columns and its figures
    assert res["parts"]["trust columns"]["calls"] == 1 and res["parts"]["plots"]["calls"] >= 2
    kernels = {k["kernel"]: k for k in res["kernels"]}
    assert kernels["least-squares fits (LM)"]["calls"] >= 2
    assert 0 < kernels["least-squares fits (LM)"]["cpu_s"] <= res["profiled_cpu_s"]
    assert kernels["loop: score tests"]["calls"] == 0  # a kinematic run has no closed loop
    own = res["own"]
    assert sum(r["share"] for r in own) <= 1.0 + 1e-9 and own == sorted(own, key=lambda r: -r["cpu_s"])
    assert any(r["function"].startswith("torchcal/") and r["calls"] for r in own)


@pytest.mark.slow
def test_commits_are_timed_in_pairs_with_their_results_compared(campaign, tmp_path):
    """A commit against itself under two names (two trees, two runs): the same results; an unknown commit is
    refused."""
    from experiments.profile_calibration import compare_commits
    from torchcal.errors import TorchcalError

    git = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False)
    if git.returncode != 0:
        pytest.skip("compare_commits archives commits of a git checkout; this is none")
    head = git.stdout.strip()
    res = compare_commits(str(campaign), "ur5", [("HEAD", head)], 1, tmp_path)
    (pair,) = res["pairs"]
    assert len(pair["cpu_s"]["HEAD"]) == len(pair["cpu_s"][head]) == 1 and len(pair["round_ratios"]) == 1
    assert pair["same_results"] and pair["cpu_ratio"] > 0 and pair["cpu_ratio_of_minima"] == pair["cpu_ratio"]
    with pytest.raises(TorchcalError, match="git archive no-such-commit"):
        compare_commits(str(campaign), "ur5", [("no-such-commit", head)], 1, tmp_path)
