"""``torchcal fleet`` (torchcal.fleet): the manifest's checks, the tasks one after another and on a local Ray with
the same results, a refused line reported while the others go on, a killed worker's task retried or reported, and
the summary's verdicts. The Ray tests start and stop their own local instance (2 CPUs)."""

import contextlib
import io
import json
import os
import re
import sys
from pathlib import Path

import pytest

from torchcal import fleet as F
from torchcal.cli import main
from torchcal.errors import TorchcalError

try:
    import ray
except ImportError:
    ray = None
needs_ray = pytest.mark.skipif(ray is None, reason="Ray is not installed (pip install torchcal[fleet]): Ray untested")


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    """Two small simulated UR5 campaigns, their kinematic lines, a third line whose data are missing."""
    root = tmp_path_factory.mktemp("fleet")
    for s in (1, 2):
        assert (
            main(
                ["simulate", "--robot", "ur5", "--out", str(root / f"sim{s}"), "--poses", "60"]
                + ["--test-poses", "5", "--seed", str(s), "--quiet"]
            )
            == 0
        )
    m = root / "manifest.csv"
    m.write_text(
        "name,data,robot,method\nr1,sim1/train.csv,ur5,kinematic\nr2,sim2/train.csv,ur5,kinematic\n"
        "gone,missing.csv,ur5,kinematic\n"
    )
    return m


@pytest.fixture(scope="module")
def serial(manifest, tmp_path_factory):
    """The command without Ray: the same tasks one after another, and it says so."""
    out = tmp_path_factory.mktemp("serial") / "fleet"
    err = io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stderr(err):
        mp.setattr(F, "ray_available", lambda: False)
        assert main(["fleet", str(manifest), "--out", str(out)]) == 0
    assert "one after another" in err.getvalue()
    # the missing file is told before any task runs, with the manifest's line and column
    told = f"torchcal fleet: {manifest}: line 4, column 'data': "
    assert told in err.getvalue() and err.getvalue().index(told) < err.getvalue().index("torchcal fleet: r1:")
    fleet = F.FleetResult("serial", json.loads((out / "report.json").read_text())["robots"], 0.0)
    return fleet, out


def _numbers(fleet):
    return {r["name"]: (r["status"], r.get("report")) for r in fleet.results}


@pytest.mark.slow
def test_serial_fleet_writes_every_run_and_reports_the_refused_line(serial):
    fleet, out = serial
    d = json.loads((out / "report.json").read_text())
    assert d["engine"] == "serial" and d["n_lines"] == 3 and d["n_ok"] == 2 and d["n_failed"] == 1
    gone = next(r for r in d["robots"] if r["name"] == "gone")
    assert gone["status"] == "refused" and "missing.csv" in gone["error"] and gone["needs_calibration"] is None
    for name in ("r1", "r2"):
        run = json.loads((out / name / "report.json").read_text())
        row = next(r for r in d["robots"] if r["name"] == name)
        assert row["report"]["rmse_after_mm"] == run["rmse_after_mm"] > 0
        assert row["needs_calibration"] is False  # fresh, global test passed
    assert not (out / "gone").exists()
    assert "| gone | refused |" in (out / "report.md").read_text()


@pytest.mark.slow
@needs_ray
def test_ray_fleet_gives_the_serial_results(manifest, serial, tmp_path, capsys):
    """The CLI on a local Ray of 2 CPUs: every number as one after another."""
    out = tmp_path / "fleet"
    assert main(["fleet", str(manifest), "--out", str(out), "--workers", "2"]) == 0
    d = json.loads((out / "report.json").read_text())
    assert d["engine"] == "ray"
    assert {r["name"]: (r["status"], r.get("report")) for r in d["robots"]} == _numbers(serial[0])
    assert (out / "r1" / "model.pt").read_bytes() == (serial[1] / "r1" / "model.pt").read_bytes()
    err = capsys.readouterr().err
    assert "gone: refused" in err and "2 of 3 calibrated" in err


def _dies_once(line):
    """A task whose worker is killed on its first try (a marker file says whether it was tried), then calibrates."""
    mark = Path(line.data).with_suffix(".tried")
    if line.name == "always" or not mark.exists():
        mark.write_text("x")
        os._exit(1)
    return F.calibrate_line(line)


@pytest.mark.slow
@needs_ray
def test_a_killed_worker_is_retried_or_reported(manifest, tmp_path):
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    lines = F.read_manifest(manifest)[:1]
    lines += [F.Line(9, "always", lines[0].data.replace("sim1", "sim2"), "ur5", "kinematic")]
    got = {}
    F.run_ray(lines, lambda r: got.update({r["name"]: r}), 2, None, task=_dies_once)
    assert got["r1"]["status"] == "ok"  # retried after the kill
    assert got["always"]["status"] == "failed" and f"{F.RETRIES + 1} tries" in got["always"]["error"]


def test_the_manifest_is_checked_before_anything_runs(tmp_path):
    cases = {
        "name,data\nr1,a.csv\n": "line 1",
        "name,data,robot,colour\nr1,a.csv,ur5,red\n": "colour",
        "name,data,robot\nr1,a.csv,ur5\nr1,b.csv,ur5\n": "line 3, column 'name'",
        "name,data,robot\n../x,a.csv,ur5\n": "line 2, column 'name'",
        "name,data,robot,method\nr1,a.csv,ur5,magic\n": "line 2, column 'method'",
        "name,data,robot\nr1,,ur5\n": "line 2, column 'data'",
        "name,data,robot\nr1,a.csv\n": "line 2: 2 cells",
        "name,data,robot\n": "no lines",
    }
    for text, where in cases.items():
        m = tmp_path / "m.csv"
        m.write_text(text)
        with pytest.raises(TorchcalError, match=where.replace("(", r"\(")):
            F.read_manifest(m)
    out = tmp_path / "out"
    assert main(["fleet", str(m), "--out", str(out)]) == 2 and not out.exists()


def test_verdicts():
    ok = {"status": "ok", "report": {"moved": None, "global_test_passed": True, "prior": None}}
    assert F.verdict(ok) == (False, "calibrated; the model explains the data to their noise")
    moved = {
        "status": "ok",
        "report": {"moved": [{"name": "a2", "sigmas": 5.0}], "global_test_passed": True, "prior": "run"},
    }
    assert F.verdict(moved)[0] is True and "a2" in F.verdict(moved)[1]
    failed = {"status": "ok", "report": {"moved": [], "global_test_passed": False, "prior": "run"}}
    assert F.verdict(failed)[0] is True
    assert F.verdict({"status": "refused"})[0] is None


def test_missing_inputs_name_the_manifest_line_and_column(manifest, tmp_path):
    """Each line whose data file, robot or prior run is not there, found before any task (they still run, refused)."""
    (tmp_path / "empty_run").mkdir()
    m = tmp_path / "m.csv"
    data = manifest.parent / "sim1" / "train.csv"
    m.write_text(
        f"name,data,robot,prior\nok,{data},ur5,\nnodata,nothere.csv,ur5,\nnorobot,{data},ur55,\n"
        f"noprior,{data},ur5,empty_run\n"
    )
    problems = F.missing_inputs(m, F.read_manifest(m))
    assert [p.split(": ")[1] for p in problems] == [
        "line 3, column 'data'",
        "line 4, column 'robot'",
        "line 5, column 'prior'",
    ]
    assert "ur55" in problems[1] and "ur5" in problems[1].split("ur55", 1)[1]  # the valid names listed
    assert "no model.json" in problems[2]


def test_manifests_as_spreadsheets_write_them_and_names_alike(tmp_path):
    """own: a manifest saved as Excel's "CSV UTF-8" (a byte-order mark) was refused; a name with a line break in a
    quoted cell became another name without a word; 'é' composed and decomposed were two robots in one folder name;
    a data path that is a folder was called 'no such file'."""
    from torchcal.errors import TorchcalError
    from torchcal.fleet import missing_inputs, read_manifest

    (tmp_path / "d.csv").write_text("x\n")
    bom = tmp_path / "bom.csv"
    bom.write_bytes("\ufeffname,data,robot\nA,d.csv,ur5\n".encode())
    assert [ln.name for ln in read_manifest(bom)] == ["A"]
    cases = {
        'name,data,robot\n"A\nB",d.csv,ur5\n': "line 3, column 'name': 'A\\nB' holds control characters",
        "name,data,robot\n\u00e9,d.csv,ur5\ne\u0301,d.csv,ur5\n": "repeats line 2",
    }
    for k, (text, message) in enumerate(cases.items()):
        (tmp_path / f"m{k}.csv").write_text(text, encoding="utf-8")
        with pytest.raises(TorchcalError, match=re.escape(message)):
            read_manifest(tmp_path / f"m{k}.csv")
    (tmp_path / "folder.csv").write_text(f"name,data,robot\nA,{tmp_path},ur5\n")
    assert "not a regular file" in missing_inputs(tmp_path / "folder.csv", read_manifest(tmp_path / "folder.csv"))[0]
