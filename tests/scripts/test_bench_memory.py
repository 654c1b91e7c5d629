"""The memory probe (``scripts/bench_memory.py``) and the lazy imports it watches.

A command's stages nest and carry their own peaks; a kinematic calibration of a DH robot imports matplotlib only
for the report's figures and never yourdfpy, trimesh or scipy (the calibrated URDF is checked from its elements);
``import torchcal.cli`` imports none of them.
"""

import json
import subprocess
import sys

import pytest

from experiments.bench_memory import calibration, measure, table

HEAVY = ("matplotlib", "yourdfpy", "trimesh", "scipy", "pytorch_kinematics", "networkx")


@pytest.mark.slow
def test_importing_the_cli_and_the_package_imports_no_heavy_library():
    code = (
        "import sys, torchcal, torchcal.cli, torchcal.pipeline, torchcal.report; "
        f"print([m for m in {HEAVY!r} if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert json.loads(out.strip().replace("'", '"')) == []


@pytest.fixture(scope="module")
def campaign_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("mem") / "sim"
    res = measure(["simulate", "--robot", "ur5", "--poses", "120", "--test-poses", "10", "--out", str(out), "--quiet"])
    assert res["rc"] == 0 and (out / "train.csv").is_file()
    return out, res


@pytest.mark.slow
def test_stages_nest_and_carry_their_own_peak(campaign_dir):
    _, res = campaign_dir
    by = {s["stage"]: s for s in res["stages"]}
    assert {
        "command/import torchcal",
        "command/import torchcal.cli",
        "command",
        "command/simulate",
        "command/write campaign",
    } <= set(by)
    # 'import torchcal' is light (its public names load torch on first use: a Ctrl-C at start-up is caught before);
    # torch alone is ~200 MB, so the command's peak, where it is loaded, is far above the interpreter's start
    assert by["command/import torchcal"]["peak_mb"] < res["start_rss_mb"] + 50
    assert by["command"]["peak_mb"] > res["start_rss_mb"] + 50
    # an enclosing stage's peak is at least each child's, and the run's peak the largest of all
    assert by["command"]["peak_mb"] >= max(by["command/simulate"]["peak_mb"], by["command/write campaign"]["peak_mb"])
    assert res["peak_mb"] == max(s["peak_mb"] for s in res["stages"])
    assert by["command/simulate"]["calls"] == 1 and by["command/simulate"]["wall_s"] > 0
    assert "command/simulate" in table(res)


@pytest.mark.slow
def test_a_kinematic_calibration_imports_matplotlib_only_for_the_figures(campaign_dir, tmp_path):
    sim, _ = campaign_dir
    res = calibration(
        str(sim / "train.csv"),
        "ur5",
        "kinematic",
        tmp_path / "run",
        targets=["torchcal.estimate.fit:selection=selection"],
    )
    assert (tmp_path / "run" / "report.json").is_file()
    imported = {s["stage"]: set(s["imports"]) for s in res["stages"]}
    assert [st for st, mods in imported.items() if mods & {"yourdfpy", "trimesh", "scipy", "networkx"}] == []
    assert [st for st, mods in imported.items() if "matplotlib" in mods] == ["command/report/report.md and figures"]
    stages = [s["stage"] for s in res["stages"]]
    assert "command/fit/least squares/selection" in stages and "command/report/URDF reload check" in stages


def test_a_failing_command_raises_with_its_message(tmp_path):
    from torchcal.errors import TorchcalError

    with pytest.raises(TorchcalError, match=r"exit 2\).*no-such.csv"):
        measure(["calibrate", str(tmp_path / "no-such.csv"), "--robot", "ur5", "--out", str(tmp_path / "run")])


@pytest.mark.slow
def test_the_calibration_bench_times_each_stage_through_the_probe(campaign_dir, tmp_path):
    from experiments.bench_calibration import compare

    sim, _ = campaign_dir
    res = compare(str(sim / "train.csv"), "ur5", ["kinematic"], False, tmp_path)
    run = res["quiet"]["kinematic"]
    assert [s["stage"] for s in run["stages"]] == ["import", "robot", "read", "fit", "report"]
    assert all(s["calls"] >= 1 and s["wall_s"] > 0 for s in run["stages"])
    # the fit's nested stages by name, the screening's and the kinematic fit's LM solves summed under one
    assert run["parts"]["screening"]["calls"] == 1 and run["parts"]["LM"]["calls"] >= 2
    assert run["parts"]["LM"]["wall_s"] <= next(s["wall_s"] for s in run["stages"] if s["stage"] == "fit")
    report = json.loads((tmp_path / "q-kinematic" / "run" / "report.json").read_text())
    assert run["rmse_holdout_mm"] == report["rmse_after_mm"] and run["effects"] == []
    summary = res["summary"]["kinematic"]
    assert summary["quiet_wall_s"] == run["total_wall_s"] > sum(s["wall_s"] for s in run["stages"])
    assert summary["quiet_peak_mb"] == run["peak_mb"] >= max(s["peak_mb"] for s in run["stages"])


def test_a_stage_in_a_worker_thread_nests_on_its_own_stack():
    import threading
    import time

    from experiments._memprobe import Meter

    meter = Meter(reset=False)
    meter.enter("fit")
    meter.enter("network")
    worker = threading.Thread(target=meter.wrap(lambda: time.sleep(0.05), "gp"))
    worker.start()  # the GP beside the network: its own stack, named under where the main thread is
    time.sleep(0.01)
    meter.exit()  # the network ends first; the GP's stage does not end it
    worker.join()
    meter.exit()
    rec = meter.records
    assert set(rec) == {"fit", "fit/network", "fit/network/gp"}
    assert rec["fit/network/gp"]["wall_s"] >= 0.05 > rec["fit/network"]["wall_s"]
    assert rec["fit"]["wall_s"] >= rec["fit/network/gp"]["wall_s"] and all(r["calls"] == 1 for r in rec.values())
