"""An export of a run with effects stands alone: the file holds the run's stand-alone geometry (the better of its
kinematic calibration and a refit to the full model on the held-out rows), says what it is and what it predicts alone,
and ``check-export`` reads it back to the numbers the run recorded."""

import json
import re

import pytest
import torch

from torchcal.cli import main
from torchcal.effects import MeasurementModel
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.sim.campaign import EffectSpec, SimConfig, simulate
from torchcal.stats import rmse
from torchcal.use.export import check_export, export_run, exported_model

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A small UR5 campaign with gravity compliance at joint 2: its default run (which names the compliance) and its
    kinematic run, written as run directories."""
    c = simulate(
        SimConfig(robot="ur5", poses=160, test_poses=60, seed=3, effects=[EffectSpec("compliance", joint=2, size=2e-4)])
    )
    root = tmp_path_factory.mktemp("export")
    out = {"campaign": c}
    for method in ("auto", "kinematic"):
        run = calibrate("ur5", c.train, Options.of(method=method, seed=0, holdout=0.25, trajectory=False))
        out[method] = write_run(run, root / method)
    return out


def test_the_default_run_keeps_a_standalone_geometry_chosen_on_its_held_out_rows(runs):
    meta = json.loads((runs["auto"] / "model.json").read_text())
    assert meta["effects"], "the campaign's compliance must be named for this test to mean anything"
    alone = meta["standalone"]
    assert alone["source"] in alone["candidates_mm"]
    assert alone["rmse_holdout_mm"] == min(alone["candidates_mm"].values())
    # the geometry fitted with the compliance leans on it: alone it is worse than the stand-alone choice
    assert alone["rmse_holdout_mm"] < alone["rmse_cofitted_mm"]
    assert alone["rmse_full_mm"] < alone["rmse_holdout_mm"]


@pytest.mark.parametrize("fmt,suffix", [("dh", ".yaml"), ("urdf", ".urdf")])
@pytest.mark.parametrize("geometry", ["standalone", "cofitted"])
def test_an_export_says_what_it_predicts_alone_and_check_export_reads_it_back(runs, tmp_path, fmt, suffix, geometry):
    f = tmp_path / f"robot{suffix}"
    ex = export_run(runs["auto"], fmt, f, geometry=geometry)
    meta = json.loads((runs["auto"] / "model.json").read_text())["standalone"]
    want = meta["rmse_holdout_mm"] if geometry == "standalone" else meta["rmse_cofitted_mm"]
    assert ex.which == geometry and ex.rmse_mm == want
    text = f.read_text()
    m = re.search(r"this chain alone: ([0-9.]+) mm held-out .*; the full run: ([0-9.]+) mm held-out", text)
    assert m is not None, text[:600]
    assert float(m.group(1)) == pytest.approx(want, abs=1e-4)
    assert float(m.group(2)) == pytest.approx(meta["rmse_full_mm"], abs=1e-4)
    assert "NOT in this file: compliance(joint 2)" in text
    c = check_export(runs["auto"], f)
    assert c.which == geometry and c.tip == "flange"
    assert c.fk_gap_mm < 1e-9
    assert c.rmse_mm == pytest.approx(want, rel=1e-9)


def test_the_standalone_file_predicts_the_test_rows_better_alone_than_the_cofitted_one(runs, tmp_path):
    test = runs["campaign"].test
    got = {}
    for geometry in ("standalone", "cofitted"):
        model = exported_model(runs["auto"], geometry).model
        got[geometry] = rmse(errors(MeasurementModel(model.robot), test, trajectory=False))
    assert got["standalone"] < got["cofitted"]


def test_a_run_without_effects_exports_its_own_geometry_and_says_so(runs, tmp_path):
    ex = export_run(runs["kinematic"], "dh", tmp_path / "k.yaml")
    assert ex.which == "run" and not ex.left_out
    rep = json.loads((runs["kinematic"] / "report.json").read_text())
    assert ex.rmse_mm == pytest.approx(rep["rmse_after_mm"])
    assert "this chain alone is the full run" in (tmp_path / "k.yaml").read_text()
    c = check_export(runs["kinematic"], tmp_path / "k.yaml")
    assert c.fk_gap_mm < 1e-9 and c.rmse_mm == pytest.approx(rep["rmse_after_mm"], rel=1e-9)


def test_check_export_on_the_command_line(runs, tmp_path, capsys):
    f = tmp_path / "r.urdf"
    assert main(["export", str(runs["auto"]), "--format", "urdf", "--out", str(f)]) == 0
    err = capsys.readouterr().err
    assert "this chain alone:" in err and "the full run:" in err
    assert main(["check-export", str(runs["auto"]), str(f)]) == 0
    out = capsys.readouterr().out
    assert "loaded to link 'flange'" in out and "held-out RMSE" in out
    bad = tmp_path / "r.txt"
    bad.write_text("x")
    assert main(["check-export", str(runs["auto"]), str(bad)]) == 2
    assert "check-export reads DH files" in capsys.readouterr().err


def test_a_file_of_another_robot_is_refused(runs, tmp_path):
    from torchcal.errors import OptionError

    with pytest.raises(OptionError, match="joints"):
        check_export(runs["auto"], torch_robot_file(tmp_path))


def torch_robot_file(tmp_path):
    """A 7-joint DH file (the built-in arm7_dh): not the run's 6-joint UR5."""
    from torchcal.robot.load import resolve_robot_spec

    src = resolve_robot_spec("arm7_dh")
    f = tmp_path / "arm7.yaml"
    f.write_text(src.read_text())
    return f


def test_check_export_compares_the_file_with_the_run_not_with_itself(runs, tmp_path):
    f = tmp_path / "moved.yaml"
    export_run(runs["auto"], "dh", f)
    text = f.read_text()
    # move the first joint's d by 1 mm: the check must see it
    m = re.search(r"d: (-?[0-9.e-]+)", text)
    text = text.replace(m.group(0), f"d: {float(m.group(1)) + 1e-3!r}", 1)
    f.write_text(text)
    c = check_export(runs["auto"], f)
    assert c.fk_gap_mm == pytest.approx(1.0, rel=1e-6)
    assert torch.isfinite(torch.tensor(c.rmse_mm))


@pytest.mark.parametrize("suffix", [".yaml", ".urdf"])
def test_a_run_of_its_own_export_keeps_the_runs_sigma(runs, tmp_path, suffix):
    """Issue 46 saw sigma 10-25x too large where --robot was a run's export; here the export of a kinematic run, used
    as --robot for the same rows, gives the same held-out error and the same sigma at the test rows."""
    from torchcal.effects import Context
    from torchcal.robot.load import calibrated_flange
    from torchcal.use.rundir import load_model, row_trust

    f = tmp_path / f"own{suffix}"
    export_run(runs["kinematic"], "dh" if suffix == ".yaml" else "urdf", f)
    c = runs["campaign"]
    again = write_run(
        calibrate(
            str(f),
            c.train,
            Options.of(method="kinematic", seed=0, holdout=0.25, trajectory=False),
            tip_link=calibrated_flange(f),  # as --robot loads a torchcal URDF: to its flange (None for a DH file)
        ),
        tmp_path / "again",
    )
    ctx = Context.from_measurements(c.test, trajectory=False)
    sig = {}
    for name, rd in (("first", runs["kinematic"]), ("again", again)):
        model, meta = load_model(rd)
        sig[name] = row_trust(rd, model, meta, ctx).sigma
        e = (model(ctx).detach() - c.test.p).abs()
        assert float((e < 3 * sig[name]).all(dim=1).float().mean()) >= 0.95
    ratio = (sig["again"] / sig["first"]).median()
    assert 0.8 < float(ratio) < 1.25, float(ratio)
