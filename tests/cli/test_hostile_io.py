"""Hostile inputs, round 2 (issue 28, items 1-8, 19, 20): nothing torchcal did not write is replaced or
deleted, no input hangs the command or reads without end, and crafted run directories, sizes and seeds are
refused before any work with exit code 2 and a message naming the file.

The second half holds further cases of the same kinds; each says whether it found a bug in the code before
this file was written ("bug before") or held already ("held").
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import _cli
import pytest
import torch
from _cli import ROOT, calibrate, cli_simulate, deadline, snapshot

import torchcal
from torchcal import _inputs, _outdir
from torchcal.cli import main
from torchcal.effects import CorrectionNet, LearnedEffect, MeasurementModel
from torchcal.errors import MeasurementFileError, OptionError, RobotSpecError


def refused(capsys, *names) -> str:
    """The command's stderr, asserted to be one clean error (``error:``) naming every one of ``names``."""
    err = _cli.refused(capsys, *names)
    assert "error:" in err, err
    return err


def predict(run, data, out, *extra) -> int:
    return main(["predict", str(run), str(data), "--out", str(out), "--quiet", *extra])


def fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def sparse(path: Path, size: int) -> Path:
    """A file of ``size`` bytes that takes no disk space (all zeros)."""
    with open(path, "wb") as f:
        f.truncate(size)
    return path


def copy_run(run_dir: Path, where: Path) -> Path:
    shutil.copytree(run_dir, where)
    return where


# -------------------------------------------------------------------------------- item 1: --out ending in '..'


def test_out_ending_in_dotdot_replaces_the_run_it_names_and_nothing_above(run_dir, campaign, tmp_path, capsys):
    home = tmp_path / "home"
    run = copy_run(run_dir, home / "RUN")
    (home / "keep.txt").write_text("the grandparent's neighbour")
    out = f"{run}/robot/.."  # resolves to RUN, a marked run: replace RUN, never rename '<parent>/..'
    assert calibrate(campaign / "train.csv", out) == 0
    assert _outdir.is_marked(run) and (run / "report.json").is_file()
    assert (home / "keep.txt").read_text() == "the grandparent's neighbour"
    assert sorted(p.name for p in home.iterdir()) == ["RUN", "keep.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["home"]


def test_out_through_a_symlinked_parent_and_dotdot_acts_on_the_real_run(run_dir, campaign, tmp_path, capsys):
    real = copy_run(run_dir, tmp_path / "deep" / "er" / "RUN")
    (tmp_path / "link").symlink_to(real)
    # textually 'link/robot/..' is 'link'; the kernel walks to the real RUN: the checks and the rename agree
    assert calibrate(campaign / "train.csv", f"{tmp_path / 'link'}/robot/..") == 0
    assert (tmp_path / "link").is_symlink() and os.readlink(tmp_path / "link") == str(real)
    assert _outdir.is_marked(real)
    assert sorted(p.name for p in real.parent.iterdir()) == ["RUN"]


@pytest.mark.parametrize("kind", ["link-to-run", "link-dot", "dangling"])
def test_a_symlink_as_out_is_refused_and_left_alone(kind, run_dir, campaign, tmp_path, capsys):
    target = copy_run(run_dir, tmp_path / "RUN") if kind != "dangling" else tmp_path / "nowhere"
    link = tmp_path / "out"
    link.symlink_to(target)
    before = snapshot(tmp_path)
    assert calibrate(campaign / "train.csv", f"{link}/." if kind == "link-dot" else link) == 2
    refused(capsys, "symbolic link")
    assert link.is_symlink() and os.readlink(link) == str(target) and snapshot(tmp_path) == before


def test_resolve_out_keeps_a_last_symlink_and_resolves_dots(tmp_path):
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "l").symlink_to(tmp_path / "a" / "b")
    real = Path(os.path.realpath(tmp_path))
    assert _outdir.resolve_out(tmp_path / "l") == real / "l"  # the link itself, never its target
    assert _outdir.resolve_out(f"{tmp_path / 'l'}/..") == real / "a"
    assert _outdir.resolve_out(f"{tmp_path / 'l'}/x") == real / "a" / "b" / "x"


# ------------------------------------------------------------------ item 2: output files torchcal did not write


def test_predict_out_refuses_a_file_it_did_not_write_unless_forced(run_dir, campaign, tmp_path, capsys):
    out = tmp_path / "pred.csv"
    out.write_text("the user's spreadsheet\n")
    assert predict(run_dir, campaign / "test.csv", out) == 2
    refused(capsys, str(out), "--force")
    assert out.read_text() == "the user's spreadsheet\n"
    assert predict(run_dir, campaign / "test.csv", out, "--force") == 0
    assert out.read_text().startswith("# written_by: torchcal predict\n")
    assert predict(run_dir, campaign / "test.csv", out) == 0  # torchcal's own file: replaced without --force
    # the mark is a comment line of the measurement format: the file still reads, the mark as metadata
    back = torchcal.read_measurements(out, require_positions=True)
    assert back.meta["written_by"] == "torchcal predict" and back.n == 20


def test_compensate_out_refuses_a_file_it_did_not_write_unless_forced(run_dir, campaign, tmp_path, capsys):
    targets = tmp_path / "targets.csv"
    rows = (campaign / "test.csv").read_text().splitlines()
    body = [r for r in rows if not r.startswith("#")][:4]
    targets.write_text("\n".join(body) + "\n")
    out = tmp_path / "joints.csv"
    out.write_text("q1,q2\n1,2\n")
    cmd = ["compensate", str(run_dir), str(targets), "--out", str(out), "--quiet"]
    assert main(cmd) == 2
    refused(capsys, str(out), "--force")
    assert out.read_text() == "q1,q2\n1,2\n"
    assert main([*cmd, "--force"]) == 0
    assert out.read_text().startswith("# written_by: torchcal compensate\n")
    assert main(cmd) == 0


def test_convert_out_refuses_a_file_it_did_not_write_before_reading_the_source(tmp_path, capsys):
    src = tmp_path / "measurements_x.csv"
    src.write_text("not;an;ipa;file\n")
    out = tmp_path / "converted.csv"
    out.write_text("precious\n")
    cmd = ["convert", str(src), "--from", "ipa-robot-accuracy", "--out", str(out), "--quiet"]
    assert main(cmd) == 2
    refused(capsys, str(out), "torchcal did not write it")
    assert main([*cmd, "--force"]) == 2  # past the --out check; the source itself is refused, out untouched
    err = refused(capsys, str(src))
    assert "torchcal did not write it" not in err and out.read_text() == "precious\n"


def test_a_marker_that_is_not_on_the_first_line_does_not_count(run_dir, campaign, tmp_path, capsys):
    out = tmp_path / "pred.csv"
    out.write_text("my notes\n# written_by: torchcal predict\n")
    assert predict(run_dir, campaign / "test.csv", out) == 2
    refused(capsys, str(out))
    assert out.read_text().startswith("my notes")


# --------------------------------------------------------------- item 3: a marked run holding the user's files


@pytest.mark.parametrize("what", ["file", "folder", "symlink", "fifo", "file-in-robot"])
def test_a_marked_run_holding_what_torchcal_did_not_write_is_refused(what, run_dir, campaign, tmp_path, capsys):
    run = copy_run(run_dir, tmp_path / "run")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "data.bin").write_text("elsewhere")
    name = {
        "file": "NOTES.txt",
        "folder": "photos/",
        "symlink": "shortcut",
        "fifo": "pipe",
        "file-in-robot": "robot/NOTES.txt",
    }[what]
    if what in ("file", "file-in-robot"):
        (run / name).write_text("the user's notes")
    elif what == "folder":
        (run / "photos").mkdir()
        (run / "photos" / "cell.jpg").write_bytes(b"\xff\xd8")
    elif what == "symlink":
        (run / name).symlink_to(outside)
    else:
        fifo(run / name)
    before = snapshot(outside)
    listing = sorted(str(p.relative_to(run)) for p in run.rglob("*"))
    with deadline(60):
        assert calibrate(campaign / "train.csv", run) == 2
    refused(capsys, name, "did not write")
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*")) == listing and snapshot(outside) == before


def test_the_marker_lists_what_was_written(run_dir):
    doc = json.loads((run_dir / _outdir.MARKER).read_text())
    assert doc["format"] == "torchcal-run" and doc["written_by"] == "calibrate"
    assert {"report.json", "model.json", "model.pt", "robot/"} <= set(doc["files"])
    assert set(doc["files"]) == {
        str(p.relative_to(run_dir)) + ("/" if p.is_dir() else "")
        for p in run_dir.rglob("*")
        if p.name != ".torchcal-run"
    }


def test_a_version_1_marker_allows_only_the_files_of_its_kind(run_dir, campaign, tmp_path, capsys):
    run = copy_run(run_dir, tmp_path / "run")
    (run / _outdir.MARKER).write_text('{"format": "torchcal-run", "version": 1, "written_by": "calibrate"}\n')
    for name in ("holdout.pt", "nominal.pt", "covariance_nominal.pt", "covariance_beyond.pt"):
        (run / name).unlink(missing_ok=True)  # a run of a version-1 marker wrote no held-out rows, no models beyond
    assert _outdir.foreign_entries(run) == []
    (run / "NOTES.txt").write_text("x")
    assert _outdir.foreign_entries(run) == ["NOTES.txt"]
    assert calibrate(campaign / "train.csv", run) == 2
    refused(capsys, "NOTES.txt")


# ------------------------------------------------------------------------- items 4, 5: FIFOs, devices, sizes


@pytest.mark.parametrize("role", ["data", "robot", "start"])
def test_a_fifo_as_an_input_is_refused_before_it_is_opened(role, run_dir, campaign, tmp_path, capsys):
    pipe = fifo(tmp_path / ("robot.urdf" if role == "robot" else "in.csv"))
    with deadline(30):
        if role == "data":
            assert calibrate(pipe, tmp_path / "o") == 2
            refused(capsys, pipe, "FIFO")
            assert predict(run_dir, pipe, tmp_path / "p.csv") == 2
        elif role == "robot":
            cmd = ["calibrate", str(campaign / "train.csv"), "--robot", str(pipe), "--out", str(tmp_path / "o")]
            assert main([*cmd, "--quiet"]) == 2
        else:
            targets = tmp_path / "t.csv"
            targets.write_text("x,y,z\n0.3,0.1,0.4\n")
            cmd = ["compensate", str(run_dir), str(targets), "--start", str(pipe), "--out", str(tmp_path / "j.csv")]
            assert main([*cmd, "--quiet"]) == 2
    refused(capsys, pipe, "FIFO")
    assert not (tmp_path / "o").exists() and not (tmp_path / "p.csv").exists()


@pytest.mark.parametrize("which", ["model.json", "model.pt"])
def test_a_fifo_in_a_run_directory_is_refused(which, run_dir, campaign, tmp_path, capsys):
    run = copy_run(run_dir, tmp_path / "run")
    (run / which).unlink()
    fifo(run / which)
    with deadline(30):
        assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
    refused(capsys, which, "FIFO")


@pytest.mark.parametrize("command", ["calibrate", "predict", "compensate", "convert"])
def test_dev_zero_is_refused_unread(command, run_dir, tmp_path, capsys):
    with deadline(30):
        if command == "calibrate":
            rc = calibrate("/dev/zero", tmp_path / "o")
        elif command == "predict":
            rc = predict(run_dir, "/dev/zero", tmp_path / "p.csv")
        elif command == "compensate":
            rc = main(["compensate", str(run_dir), "/dev/zero", "--out", str(tmp_path / "j.csv"), "--quiet"])
        else:
            rc = main(["convert", "/dev/zero", "--from", "ipa-robot-accuracy", "--out", str(tmp_path / "c.csv")])
    assert rc == 2
    refused(capsys, "/dev/zero", "character device")


@pytest.mark.parametrize(
    "kind, size", [("measurement file", 256 * 2**20 + 1), ("model.json", 16 * 2**20 + 1), ("model.pt", 2**30 + 1)]
)
def test_inputs_larger_than_their_kind_are_refused_unread(kind, size, run_dir, campaign, tmp_path, capsys):
    if kind == "measurement file":
        big = sparse(tmp_path / "big.csv", size)
        with deadline(30):
            assert calibrate(big, tmp_path / "o") == 2
        refused(capsys, big, "larger than a measurement file can be", "256 MiB")
    else:
        run = copy_run(run_dir, tmp_path / "run")
        sparse(run / kind, size)
        with deadline(30):
            assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
        refused(capsys, kind, f"larger than a {kind} can be")


def test_read_bounded_refuses_a_file_that_grows_past_its_limit(tmp_path, monkeypatch):
    f = tmp_path / "f.csv"
    f.write_text("q1\n" * 100)
    monkeypatch.setitem(_inputs.LIMITS, "measurement file", 50)
    with pytest.raises(MeasurementFileError, match="larger than a measurement file"):
        torchcal.read_measurements(f, require_positions=False)


# ------------------------------------------------------------------------------------------ item 6: sizes


@pytest.mark.parametrize(
    "opts, message",
    [
        (["--trajectory", "--samples", "1000000000"], "at most 100,000"),
        (["--poses", "1e12"], "at most 100,000"),
        (["--poses", "1000000000000"], "at most 100,000"),
        (["--test-poses", "100001"], "at most 100,000"),
        (["--poses", "1.5"], "whole number"),
        (["--poses", "nan"], "whole number"),
    ],
)
def test_simulate_sizes_are_bounded(opts, message, tmp_path, capsys):
    with deadline(30), pytest.raises(SystemExit) as e:
        cli_simulate(tmp_path / "s", *opts)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "s").exists()


# ----------------------------------------------------------------------------------- item 7: crafted runs


def learned_run(run_dir: Path, where: Path, edit=None) -> Path:
    """A copy of ``run_dir`` whose model carries a 6-29-3 correction network; ``edit(effect_config)`` crafts it."""
    run = copy_run(run_dir, where)
    model, meta = torchcal.use.rundir.load_model(run)
    effect = LearnedEffect(CorrectionNet(model.robot.dof, 29, seed=0))
    torch.save(MeasurementModel(model.robot, [effect]).state_dict(), run / "model.pt")
    cfg = {"class": "LearnedEffect", **effect.config()}
    if edit is not None:
        cfg = edit(cfg)
    meta["effects"] = [cfg]
    (run / "model.json").write_text(json.dumps(meta))
    return run


def test_a_well_formed_learned_run_loads(run_dir, campaign, tmp_path, capsys):
    run = learned_run(run_dir, tmp_path / "run")
    assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 0


def gate(n_region, cls="RegionGate", key="n_region"):
    """A region gate around the run's effect (``cls`` and ``key``: as runs written before ``region`` named them)."""

    def edit(cfg):
        return {"class": cls, "inner": cfg, "length": 1.0, key: n_region, "dof": 6}

    return edit


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c: {**c, "hidden": 2_000_000_000}, "hidden: 2000000000 is outside 1..100000"),
        (lambda c: {**c, "hidden": -1}, "hidden: -1 is outside"),
        (lambda c: {**c, "hidden": 1e12}, "must be a whole number"),
        (lambda c: {**c, "hidden": 5000}, "larger than the"),  # within the cap, more than model.pt holds
        (lambda c: {**c, "hidden": 30}, "does not match"),  # plausible, disagrees with the tensors
        (gate(10**12), "n_region: 1000000000000 is outside"),
        (gate(10**12, "SupportGate", "n_support"), "n_support: 1000000000000 is outside"),  # an older run's names
        (gate(1e12), "must be a whole number"),
        (lambda c: {"class": "GPCorrection", "dof": 6, "n_inducing": 10**9}, "n_inducing: 1000000000"),
        (lambda c: {"class": "Compliance", "joint": 7}, "joint 7 is not a joint of robot"),
        (lambda c: {"class": "Compliance", "joint": 0}, "joint 0 is not a joint of robot"),
        (lambda c: {"class": "Compliance", "joint": 2, "payload": 1e400}, "beyond the range of a float"),
        (lambda c: {"class": "Compliance", "joint": 2, "payload": float("nan")}, "NaN is not a JSON number"),
    ],
)
def test_crafted_model_json_is_refused_before_anything_is_built(edit, message, run_dir, campaign, tmp_path, capsys):
    run = learned_run(run_dir, tmp_path / "run", edit)
    text = (run / "model.json").read_text().replace('"payload": Infinity', '"payload": 1e400')
    (run / "model.json").write_text(text)
    with deadline(30):
        assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
    refused(capsys, "model.json" if message != "does not match" else "model.pt", message)
    assert not (tmp_path / "p.csv").exists()


# ------------------------------------------------------------------------------------ item 8: deep nesting


def test_deeply_nested_yaml_is_refused_quickly(tmp_path):
    f = tmp_path / "deep.yaml"
    f.write_text("name: r\njoints: " + "[" * 20000 + "]" * 20000 + "\n")
    with deadline(10), pytest.raises(RobotSpecError, match="nested more than 64 levels"):
        torchcal.load_robot(f)


def test_deeply_nested_model_json_is_refused_quickly(run_dir, campaign, tmp_path, capsys):
    run = copy_run(run_dir, tmp_path / "run")
    (run / "model.json").write_text("[" * 200_000 + "]" * 200_000)
    with deadline(10):
        assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
    refused(capsys, "model.json", "nested more than 64 levels")


# ------------------------------------------------------------------------------------------- item 19: seeds


@pytest.mark.parametrize("seed", [str(2**64), str(2**63), "-1", "1e30"])
@pytest.mark.parametrize("command", ["simulate", "calibrate", "demo"])
def test_seeds_out_of_range_are_clear_errors(command, seed, campaign, tmp_path, capsys):
    out = str(tmp_path / "o")
    argv = {
        "simulate": ["simulate", "--robot", "ur5", "--out", out],
        "calibrate": ["calibrate", str(campaign / "train.csv"), "--robot", "ur5", "--out", out],
        "demo": ["demo", "--out", out],
    }[command]
    with pytest.raises(SystemExit) as e:
        main([*argv, f"--seed={seed}", "--quiet"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--seed" in err and "2**63 - 1" in err and "Traceback" not in err


def test_the_largest_seed_works(tmp_path):
    assert cli_simulate(tmp_path / "s", "--poses", "30", "--test-poses", "5", "--seed", str(2**63 - 1)) == 0


# --------------------------------------------------------------------------------- item 20: Ctrl-C at start


# A real SIGINT, delivered while 'import torch' runs: a meta-path hook sends it when torch is first imported. Python
# keeps SIGINT ignored where its parent ignored it (a test worker after Ray had its turn did), so the script takes
# the handler a terminal's command gets.
_INTERRUPT_AT_TORCH = """
import os, runpy, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)
class Hook:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None
sys.meta_path.insert(0, Hook())
sys.argv = ["torchcal", "simulate", "--robot", "ur5", "--out", sys.argv[1]]
runpy.run_module("torchcal", run_name="__main__")
"""


def test_ctrl_c_while_torch_loads_exits_130_with_one_line(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run(
        [sys.executable, "-c", _INTERRUPT_AT_TORCH, str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "interrupted" in proc.stderr, proc.stderr
    assert not (tmp_path / "o").exists()


def test_import_torchcal_is_light_and_the_entry_point_is_the_light_one():
    code = "import sys, torchcal._entry; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.stdout.strip() == "False", out.stderr
    assert 'torchcal = "torchcal._entry:main"' in (ROOT / "pyproject.toml").read_text()


def test_the_lazy_package_keeps_its_public_names():
    for name in torchcal.__all__:
        assert getattr(torchcal, name) is not None
    assert torchcal.use.rundir.load_model is not None  # sub-packages load on first use
    with pytest.raises(AttributeError):
        torchcal.no_such_thing  # noqa: B018


# ================================================================== further hostile cases of the same kinds


def test_own_a_fifo_named_model_json_in_an_unmarked_out_does_not_hang(campaign, tmp_path, capsys):
    """bug before: an unmarked --out is checked for an earlier torchcal's run by reading its model.json, which
    blocked on a FIFO (on the old code the test's own deadline, a TimeoutError, is an OSError the check caught:
    the hang passed as a refusal until tests/_cli.deadline raised something else)."""
    out = tmp_path / "out"
    out.mkdir()
    fifo(out / "model.json")
    with deadline(30):
        assert calibrate(campaign / "train.csv", out) == 2
    refused(capsys, "not a torchcal output directory")


def test_own_a_fifo_as_the_ipa_source_is_refused(tmp_path, capsys):
    """bug before: convert blocked reading a FIFO source (past the 30 s deadline)."""
    pipe = fifo(tmp_path / "measurements_x.csv")
    with deadline(30):
        assert main(["convert", str(pipe), "--from", "ipa-robot-accuracy", "--out", str(tmp_path / "c.csv")]) == 2
    refused(capsys, pipe, "FIFO")


def test_own_a_symlink_to_dev_zero_as_data_is_refused(tmp_path, capsys):
    """bug before: the link was followed into an endless read (16 GB in under a minute before it was stopped)."""
    link = tmp_path / "data.csv"
    link.symlink_to("/dev/zero")
    with deadline(30):
        assert calibrate(link, tmp_path / "o") == 2
    refused(capsys, link, "character device")


def test_own_a_dangling_symlink_as_predict_out_is_not_replaced(run_dir, campaign, tmp_path, capsys):
    """bug before: the link was replaced by a regular file (it passed as 'absent')."""
    link = tmp_path / "pred.csv"
    link.symlink_to(tmp_path / "later" / "pred.csv")
    assert predict(run_dir, campaign / "test.csv", link) == 2
    refused(capsys, "symbolic link")
    assert link.is_symlink()


def test_own_a_symlink_to_a_users_file_as_compensate_out_is_refused(run_dir, campaign, tmp_path, capsys):
    """bug before: the link was silently replaced by the output (exit 0; --force is new, the old code needed
    none)."""
    mine = tmp_path / "mine.csv"
    mine.write_text("# written_by: torchcal compensate\nq1\n")  # even a torchcal file, reached through a link
    link = tmp_path / "joints.csv"
    link.symlink_to(mine)
    targets = tmp_path / "t.csv"
    targets.write_text("x,y,z\n0.3,0.1,0.4\n")
    assert main(["compensate", str(run_dir), str(targets), "--out", str(link), "--quiet", "--force"]) == 2
    refused(capsys, "symbolic link")
    assert link.is_symlink() and mine.read_text().endswith("q1\n")


def test_own_a_fifo_as_predict_out_is_refused(run_dir, campaign, tmp_path, capsys):
    """held: an existing --out that is not a regular file was refused already."""
    pipe = fifo(tmp_path / "p.csv")
    with deadline(30):
        assert predict(run_dir, campaign / "test.csv", pipe, "--force") == 2
    refused(capsys, "not a regular file")


def test_own_a_listed_file_turned_into_a_folder_is_refused(run_dir, campaign, tmp_path, capsys):
    """bug before: report.md replaced by the user's folder of the same name was deleted with the run (exit 0)."""
    run = copy_run(run_dir, tmp_path / "run")
    (run / "report.md").unlink()
    (run / "report.md").mkdir()
    (run / "report.md" / "draft.txt").write_text("mine")
    assert calibrate(campaign / "train.csv", run) == 2
    refused(capsys, "report.md/")
    assert (run / "report.md" / "draft.txt").read_text() == "mine"


def test_own_a_users_file_in_a_simulated_campaign_is_refused(campaign, tmp_path, capsys):
    """bug before: re-simulating into a campaign deleted 'train.csv.bak' the user had saved beside it (exit 0)."""
    sim = tmp_path / "sim"
    shutil.copytree(campaign, sim)
    (sim / "train.csv.bak").write_text("my edited copy")
    assert cli_simulate(sim, "--poses", "30", "--test-poses", "5") == 2
    refused(capsys, "train.csv.bak")
    assert (sim / "train.csv.bak").read_text() == "my edited copy"


def test_own_a_users_file_in_the_demos_nested_run_is_refused(tmp_path, capsys):
    """bug before (by the code: a marked directory was replaced whatever it held): a demo output's run/ folder
    lost the user's files when the demo (or a calibration into run/) wrote again. Built by hand: the demo itself
    takes minutes."""
    demo = tmp_path / "demo"
    with _outdir.replace_dir(demo, kind="demo") as tmp:
        (tmp / "summary.json").write_text("{}")
        (tmp / "run").mkdir()
        _outdir.mark(tmp / "run", "calibrate")
        (tmp / "run" / "report.json").write_text("{}")
    assert _outdir.foreign_entries(demo) == [] and _outdir.foreign_entries(demo / "run") == []
    assert json.loads((demo / "run" / _outdir.MARKER).read_text())["files"] == ["report.json"]
    (demo / "run" / "NOTES.txt").write_text("mine")
    assert _outdir.foreign_entries(demo) == ["run/NOTES.txt"]
    with pytest.raises(OptionError, match="NOTES.txt"):
        _outdir.check_out_dir(demo / "run")


def test_own_a_huge_marker_is_not_read_whole(tmp_path):
    """held in outcome, but the old code read the marker whole (1 GiB here); now at most 1 MiB is read."""
    d = tmp_path / "d"
    d.mkdir()
    sparse(d / _outdir.MARKER, 2**30)
    assert not _outdir.is_marked(d)


def test_own_a_fifo_marker_does_not_hang(tmp_path):
    """held: a marker that is not a regular file never counted."""
    d = tmp_path / "d"
    d.mkdir()
    fifo(d / _outdir.MARKER)
    with deadline(10):
        assert not _outdir.is_marked(d)


def test_own_model_json_with_duplicate_keys_is_refused(run_dir, campaign, tmp_path, capsys):
    """bug before: 'effects' given twice in model.json silently took the last."""
    run = copy_run(run_dir, tmp_path / "run")
    text = (run / "model.json").read_text().replace("{", '{"effects": [{"class": "Compliance", "joint": 2}],', 1)
    (run / "model.json").write_text(text)
    assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
    refused(capsys, "model.json", "appears twice")


def test_own_model_json_with_thousands_of_effects_is_refused(run_dir, campaign, tmp_path, capsys):
    """held in outcome (exit 2), but only after all 100,000 effects were built and model.pt disagreed; now refused
    before anything is built."""
    run = copy_run(run_dir, tmp_path / "run")
    meta = json.loads((run / "model.json").read_text())
    meta["effects"] = [{"class": "Compliance", "joint": 2}] * 100_000
    (run / "model.json").write_text(json.dumps(meta))
    with deadline(30):
        assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
    refused(capsys, "model.json", "more than 1000 effects")


def test_own_deeply_nested_support_gates_are_refused(run_dir, campaign, tmp_path, capsys):
    """bug before: 5,000 region gates nested in one another ended in a RecursionError (an internal error)."""
    run = copy_run(run_dir, tmp_path / "run")
    meta = json.loads((run / "model.json").read_text())
    text = json.dumps(meta)
    inner = '{"class": "LearnedEffect", "dof": 6, "hidden": 29}'
    for _ in range(5000):
        inner = f'{{"class": "RegionGate", "inner": {inner}, "length": 1.0, "n_region": 1, "dof": 6}}'
    (run / "model.json").write_text(text.replace('"effects": []', f'"effects": [{inner}]'))
    with deadline(30):
        assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
    refused(capsys, "model.json", "nested more than 64")


def test_own_a_robot_file_inside_the_run_that_is_a_fifo(run_dir, campaign, tmp_path, capsys):
    """held: the run's robot copy as a FIFO was never opened (a clear error, now naming the FIFO)."""
    run = copy_run(run_dir, tmp_path / "run")
    robot_file = run / json.loads((run / "model.json").read_text())["robot_file"]
    robot_file.unlink()
    fifo(robot_file)
    with deadline(30):
        assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
    refused(capsys, robot_file.name, "FIFO")


def test_own_a_robot_description_of_9_mib_is_refused_unread(campaign, tmp_path, capsys):
    """held: robot descriptions were capped at 8 MiB already (now by the shared reader)."""
    big = sparse(tmp_path / "big.urdf", 9 * 2**20)
    assert main(["calibrate", str(campaign / "train.csv"), "--robot", str(big), "--out", str(tmp_path / "o")]) == 2
    refused(capsys, big, "larger than a robot description")


def test_own_block_yaml_nested_65_levels_is_refused(tmp_path):
    """held: the old code refused it with another message; now refused by depth, naming the line."""
    lines = ["name: r", "joints:"] + [" " * (2 * k + 2) + "-" for k in range(66)]
    f = tmp_path / "deep.yaml"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(RobotSpecError, match="nested more than 64 levels"):
        torchcal.load_robot(f)


def test_own_a_predict_out_of_a_torchcal_file_inside_the_run_is_still_refused(run_dir, campaign, tmp_path, capsys):
    """held: --out inside the run directory (an input) is refused even with --force."""
    run = copy_run(run_dir, tmp_path / "run")
    assert predict(run, campaign / "test.csv", run / "report.md", "--force") == 2
    refused(capsys, "input directory")


def test_own_sizes_and_seeds_written_as_floats_are_taken_when_whole(tmp_path):
    """changed: the old code refused '3e1' ('expected a whole number'); a whole number written as a float is now
    taken, so that '--poses 1e12' is told it is too large rather than not a number."""
    assert cli_simulate(tmp_path / "a", "--poses", "3e1", "--test-poses", "5", "--seed", "1e3") == 0
    assert cli_simulate(tmp_path / "b", "--poses", "30", "--test-poses", "5", "--seed", "1000") == 0
    assert (tmp_path / "a" / "train.csv").read_bytes() == (tmp_path / "b" / "train.csv").read_bytes()


def test_own_an_out_whose_parent_is_a_fifo_is_refused(campaign, tmp_path, capsys):
    """held: a parent that is not a directory was refused already."""
    pipe = fifo(tmp_path / "pipe")
    with deadline(30):
        assert calibrate(campaign / "train.csv", pipe / "run") == 2
    refused(capsys, "not a directory")


def test_own_predict_out_dotdot_is_a_directory(run_dir, campaign, tmp_path, capsys):
    """held: an --out file ending in '..' names a directory and is refused."""
    (tmp_path / "a").mkdir()
    assert predict(run_dir, campaign / "test.csv", f"{tmp_path / 'a'}/..") == 2
    refused(capsys, "is a directory")


def test_own_a_start_file_that_is_dev_zero(run_dir, tmp_path, capsys):
    """bug before (by the code, not run on it: it would exhaust the machine's memory): compensate --start
    /dev/zero went through the same unbounded reader as the data file."""
    targets = tmp_path / "t.csv"
    targets.write_text("x,y,z\n0.3,0.1,0.4\n")
    with deadline(30):
        cmd = ["compensate", str(run_dir), str(targets), "--start", "/dev/zero", "--out", str(tmp_path / "j.csv")]
        assert main([*cmd, "--quiet"]) == 2
    refused(capsys, "/dev/zero", "character device")


def test_own_model_pt_of_non_tensors_is_refused(run_dir, campaign, tmp_path, capsys):
    """held: a model.pt holding {'x': 1} (plain ints pass weights_only) was refused by load_state_dict (missing
    keys); now named for what it is."""
    run = copy_run(run_dir, tmp_path / "run")
    torch.save({"x": 1}, run / "model.pt")
    assert predict(run, campaign / "test.csv", tmp_path / "p.csv") == 2
    refused(capsys, "model.pt", "state dict of tensors")


def test_own_a_listed_file_replaced_by_a_symlink_is_refused(run_dir, campaign, tmp_path, capsys):
    """bug before: a plot the user replaced by a link to their own picture lost the link with the run (exit 0)."""
    run = copy_run(run_dir, tmp_path / "run")
    png = sorted(run.glob("*.png"))[0]
    mine = tmp_path / "mine.png"
    mine.write_bytes(b"\x89PNG mine")
    png.unlink()
    png.symlink_to(mine)
    assert calibrate(campaign / "train.csv", run) == 2
    refused(capsys, f"{png.name} (a symbolic link)")
    assert png.is_symlink() and mine.read_bytes() == b"\x89PNG mine"


def test_own_a_directory_as_the_data_file_is_refused(run_dir, tmp_path, capsys):
    """held: the old code said 'cannot read the file: Is a directory'; now 'is a directory, not a regular file'."""
    (tmp_path / "data.csv").mkdir()
    assert predict(run_dir, tmp_path / "data.csv", tmp_path / "p.csv") == 2
    refused(capsys, "data.csv", "is a directory")


def test_own_a_urdf_replaced_by_a_fifo_during_the_fit_does_not_hang_the_export(tmp_path):
    """held: the URDF export reads the robot's own file again after the fit, but only a regular file (else it
    writes the URDF from the model); that read is now bounded too."""
    from torchcal.robot.export import write_urdf

    src = tmp_path / "arm.urdf"
    shutil.copy(ROOT / "robots" / "ur5.urdf", src)
    robot = torchcal.load_robot(src)
    src.unlink()
    fifo(src)
    with deadline(30):
        write_urdf(robot, tmp_path / "out.urdf")
    assert torchcal.load_robot(tmp_path / "out.urdf").dof == 6
