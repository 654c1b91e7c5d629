"""Hostile inputs to the torchcal command: nothing is lost, nothing crashes, nothing hangs.

Every refusal is an exit code 2 with a message saying what was expected; an unexpected exception is
exit 1 with a one-line summary (the traceback only with --debug).
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch
from _cli import calibrate, cli_simulate, deadline, snapshot

import torchcal
from torchcal import _outdir
from torchcal.cli import calibration_module, main
from torchcal.errors import MeasurementFileError, OptionError, RobotSpecError, ShapeError

ROBOTS = Path(__file__).resolve().parents[2] / "robots"


def no_temporaries(parent: Path):
    left = [p.name for p in parent.iterdir() if p.name.startswith(".") and p.name != _outdir.MARKER]
    assert left == []


# ----------------------------------------------------------------------------------------- item 1: --out


def test_unmarked_directory_is_refused_and_untouched(campaign, tmp_path, capsys, monkeypatch):
    precious = tmp_path / "precious"
    (precious / "sub").mkdir(parents=True)
    (precious / "thesis.txt").write_text("draft")
    before = snapshot(tmp_path)
    # refused before any fitting: the fit is never reached
    monkeypatch.setattr(calibration_module(), "calibrate", lambda *a, **k: pytest.fail("fitted before refusing"))
    assert calibrate(campaign / "train.csv", precious) == 2
    assert "not a torchcal output directory" in capsys.readouterr().err
    assert snapshot(tmp_path) == before


def test_out_holding_the_input_is_refused(tmp_path, capsys):
    camp = tmp_path / "campaign"
    assert cli_simulate(camp, "--poses", "60") == 0
    assert (camp / _outdir.MARKER).is_file()  # simulate's directory is marked, and still not replaced:
    before = snapshot(tmp_path)
    assert calibrate(camp / "train.csv", camp) == 2
    assert "contains the input" in capsys.readouterr().err
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("case", ["file", "dot", "parent-file", "symlink"])
def test_out_that_is_not_a_replaceable_directory(case, campaign, tmp_path, capsys, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    (work / "existing").write_text("keep me")
    (work / "target").mkdir()
    out = {
        "file": work / "existing",
        "dot": Path("."),
        "parent-file": work / "existing" / "run",
        "symlink": work / "link",
    }[case]
    if case == "symlink":
        (work / "link").symlink_to(work / "target")
    monkeypatch.chdir(work)
    before = snapshot(work)
    assert calibrate(campaign / "train.csv", out) == 2
    err = capsys.readouterr().err
    assert "error: --out" in err and "Traceback" not in err
    assert snapshot(work) == before


def test_read_only_location_is_refused_before_fitting(campaign, tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        target = ro / "run"
        if os.access(ro, os.W_OK):  # root writes anywhere: take a place that is read-only for everyone
            target = Path("/proc/sys/torchcal-run")
        assert calibrate(campaign / "train.csv", target) == 2
        assert "cannot write" in capsys.readouterr().err
        assert not target.exists()
    finally:
        ro.chmod(0o755)


def test_empty_directory_is_refused_and_marked_run_is_replaced(campaign, tmp_path, capsys):
    out = tmp_path / "empty"
    out.mkdir()
    # the outside contract: replaced only when absent or an earlier torchcal run, so not even an empty one
    assert calibrate(campaign / "train.csv", out) == 2
    assert "is an empty directory" in capsys.readouterr().err and out.is_dir() and not any(out.iterdir())
    out.rmdir()
    assert calibrate(campaign / "train.csv", out) == 0
    assert (out / "report.json").is_file() and _outdir.is_marked(out)
    assert calibrate(campaign / "train.csv", out) == 0  # a marked run holding only its own files is replaced
    assert (out / "report.json").is_file() and _outdir.is_marked(out)
    no_temporaries(tmp_path)


def test_a_damaged_marker_does_not_count(tmp_path):
    out = tmp_path / "d"
    out.mkdir()
    (out / _outdir.MARKER).write_text("not json")
    (out / "data.txt").write_text("x")
    with pytest.raises(OptionError, match="not a torchcal output"):
        _outdir.check_out_dir(out)


#: files of a run directory that torchcal writes since issue 51 (the models beyond the region), unknown to earlier ones
NEWER_FILES = ("nominal.pt", "covariance_nominal.pt", "covariance_beyond.pt")


def test_an_unmarked_run_of_an_earlier_torchcal_is_replaced_but_not_with_foreign_files(run_dir, campaign, tmp_path):
    legacy = tmp_path / "legacy"
    shutil.copytree(run_dir, legacy)
    (legacy / _outdir.MARKER).unlink()
    for name in ("holdout.pt", *NEWER_FILES):  # an earlier torchcal wrote no held-out rows, no models beyond
        (legacy / name).unlink(missing_ok=True)
    assert _outdir.is_marked(legacy)  # only its own files and model.json's format: an earlier run
    (legacy / "thesis.txt").write_text("draft")
    assert not _outdir.is_marked(legacy)
    with pytest.raises(OptionError):
        _outdir.check_out_dir(legacy)
    (legacy / "thesis.txt").unlink()
    assert calibrate(campaign / "train.csv", legacy) == 0 and (legacy / _outdir.MARKER).is_file()
    demo = tmp_path / "demo"  # an earlier demo output: data/, run/, summary.json
    shutil.copytree(run_dir, demo / "run")
    (demo / "run" / _outdir.MARKER).unlink()
    for name in ("holdout.pt", *NEWER_FILES):
        (demo / "run" / name).unlink(missing_ok=True)
    (demo / "data").mkdir()
    for f in ("train.csv", "test.csv"):
        shutil.copy(campaign / f, demo / "data" / f)
    (demo / "summary.json").write_text("{}")
    assert _outdir.is_marked(demo)
    (demo / "data" / "notes.txt").write_text("mine")
    assert not _outdir.is_marked(demo)


def test_predict_never_writes_over_its_inputs(run_dir, campaign, tmp_path, capsys):
    data = tmp_path / "test.csv"
    shutil.copy(campaign / "test.csv", data)
    before = data.read_bytes()
    assert main(["predict", str(run_dir), str(data), "--out", str(data), "--quiet"]) == 2
    assert "is the input file" in capsys.readouterr().err
    assert data.read_bytes() == before
    assert main(["predict", str(run_dir), str(data), "--out", str(run_dir / "model.json"), "--quiet"]) == 2
    assert main(["predict", str(run_dir), str(data), "--out", str(tmp_path), "--quiet"]) == 2
    assert main(["predict", str(run_dir), str(data), "--out", str(tmp_path / "p" / "pred.csv"), "--quiet"]) == 0
    assert torchcal.read_measurements(tmp_path / "p" / "pred.csv").n == 20


def test_two_concurrent_writers_serialise(tmp_path):
    out = tmp_path / "out"
    inside, errors = [], []

    def writer(k):
        try:
            for _ in range(3):
                with _outdir.replace_dir(out, kind="test") as tmp:
                    inside.append(("enter", k))
                    (tmp / "who").write_text(str(k))
                    time.sleep(0.02)
                    inside.append(("leave", k))
        except Exception as e:  # noqa: BLE001 - collected and asserted below
            errors.append(e)

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    # the lock lets one writer at a time into the block: enter/leave strictly alternate, same writer
    assert len(inside) == 24
    for a, b in zip(inside[::2], inside[1::2]):
        assert a[0] == "enter" and b == ("leave", a[1])
    assert (out / "who").read_text() in {"0", "1", "2", "3"} and _outdir.is_marked(out)
    no_temporaries(tmp_path)


@pytest.mark.slow
def test_two_torchcal_processes_writing_the_same_out(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]), "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        "-m",
        "torchcal",
        "simulate",
        "--robot",
        "ur5",
        "--out",
        "same",
        "--poses",
        "30",
        "--test-poses",
        "10",
        "--quiet",
    ]
    procs = [
        subprocess.Popen([*cmd, "--seed", str(k)], cwd=tmp_path, env=env, stderr=subprocess.PIPE, text=True)
        for k in range(2)
    ]
    errs = [p.communicate(timeout=300)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    assert sorted(p.name for p in (tmp_path / "same").iterdir()) == [
        _outdir.MARKER,
        "test.csv",
        "train.csv",
        "truth.json",
    ]
    no_temporaries(tmp_path)


def test_a_killed_writer_leaves_temporaries_that_the_next_run_removes(tmp_path):
    out = tmp_path / "out"
    code = (
        "import os, signal, sys; from torchcal import _outdir\n"
        "with _outdir.replace_dir(sys.argv[1], kind='test') as tmp:\n"
        "    (tmp / 'half').write_text('x'); os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    r = subprocess.run([sys.executable, "-c", code, str(out)], env=env, capture_output=True, timeout=120)
    assert r.returncode == -signal.SIGKILL
    stale = [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert len(stale) == 1 and not out.exists()
    # a stale ".old" of a run killed between its two renames, and a user's own dot-directory to keep
    old = tmp_path / ".out.deadbeef.old"
    old.mkdir()
    _outdir.mark(old, "test")
    mine = tmp_path / ".out.mine.tmp"
    mine.mkdir()
    other = tmp_path / ".out.x.0badf00d.tmp"  # a temporary of another --out, out.x: not this run's to remove
    other.mkdir()
    _outdir.mark(other, "test")
    with _outdir.replace_dir(out, kind="test") as tmp:
        (tmp / "done").write_text("y")
    assert (out / "done").read_text() == "y"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.mine.tmp", ".out.x.0badf00d.tmp", "out"]


def test_simulate_and_demo_output_follow_the_same_rule(tmp_path, capsys):
    out = tmp_path / "notes"
    out.mkdir()
    (out / "a.txt").write_text("mine")
    assert cli_simulate(out, "--poses", "40") == 2
    assert main(["demo", "--out", str(out), "--quiet"]) == 2
    assert (out / "a.txt").read_text() == "mine" and sorted(p.name for p in out.iterdir()) == ["a.txt"]


# --------------------------------------------------------------------------- items 4, 5: errors, not tracebacks


def write(path: Path, text: str | bytes) -> Path:
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return path


@pytest.mark.parametrize(
    "body, line",
    [
        ('q1,q2,q3,q4,q5,q6,x,y,z\n0,0,0,0,0,0,1,1,"' + "9" * 200_000 + '"\n', 2),
        ('q1,q2,q3,q4,q5,q6,x,y,z\n0,0,0,0,0,0,1,1,1\n0,0,0,0,0,0,1,1,"1\n', 3),
    ],
)
def test_csv_level_garbage_names_the_line(body, line, tmp_path, capsys):
    f = write(tmp_path / "bad.csv", body)
    with pytest.raises(MeasurementFileError) as e:
        torchcal.read_measurements(f)
    assert e.value.line == line
    assert calibrate(f, tmp_path / "out") == 2
    assert f"bad.csv, line {line}" in capsys.readouterr().err


def urdf(
    tmp_path: Path,
    name="r.urdf",
    *,
    axis="0 0 1",
    origin="0 0 0.1",
    limit='lower="-3" upper="3"',
    extra_joint="",
    tail="</robot>\n",
) -> Path:
    text = f"""<?xml version="1.0"?>
<robot name="two">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="{origin}" rpy="0 0 0"/><axis xyz="{axis}"/><limit {limit} effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.3 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j3" type="fixed"><parent link="l2"/><child link="tool"/><origin xyz="0.2 0 0" rpy="0 0 0"/></joint>
  {extra_joint}
{tail}"""
    return write(tmp_path / name, text)


def test_a_good_test_urdf_loads(tmp_path):
    assert torchcal.load_robot(urdf(tmp_path)).dof == 2


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"axis": "0 0 0"}, "is not a direction"),
        ({"origin": "0 nan 0.1"}, "non-finite"),
        ({"limit": 'lower="2" upper="-2"'}, r"r\.urdf: joint 'j1': limit lower=2.0 upper=-2.0"),
        ({"tail": ""}, "not well-formed XML"),
        ({"tail": "</robot>\n<junk/>\n"}, "not well-formed XML"),
        (
            {
                "extra_joint": '<joint name="j4" type="revolute"><parent link="tool"/><child link="l3"/>'
                '<axis xyz="0 0 1"/>'
                '<limit lower="-1" upper="1" effort="1" velocity="1"/><mimic joint="nowhere"/></joint>'
                '<link name="l3"/>'
            },
            "mimics joint 'nowhere', which is not a movable joint",
        ),
    ],
)
def test_bad_urdfs_are_refused_naming_the_urdf(kwargs, match, tmp_path):
    with deadline(60), pytest.raises(RobotSpecError, match=match):
        torchcal.load_robot(urdf(tmp_path, **kwargs))


def test_bad_urdf_through_the_cli_exits_2(tmp_path, capsys):
    f = urdf(tmp_path, axis="0 0 0")
    assert main(["simulate", "--robot", str(f), "--out", str(tmp_path / "s"), "--quiet"]) == 2
    assert "r.urdf: joint 'j1'" in capsys.readouterr().err


def test_urdf_link_cycle_is_detected(tmp_path):
    text = """<robot name="loop">
  <link name="a"/><link name="b"/><link name="c"/>
  <joint name="ab" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="bc" type="revolute"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="ca" type="revolute"><parent link="c"/><child link="a"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>
"""
    f = write(tmp_path / "loop.urdf", text)
    with deadline(60), pytest.raises(RobotSpecError, match="links form a cycle"):
        torchcal.load_robot(f, base_link="a", tip_link="c")
    with deadline(60), pytest.raises(RobotSpecError, match="links form a cycle"):
        torchcal.load_robot(f)
    # a base outside the loop and a tip inside it: the walk from the tip would never reach the base
    g = write(tmp_path / "loop2.urdf", text.replace("</robot>", '<link name="r"/></robot>'))
    with deadline(60), pytest.raises(RobotSpecError, match="links form a cycle"):
        torchcal.load_robot(g, base_link="r", tip_link="c")


def test_yaml_alias_bomb_and_latin1_are_refused(tmp_path):
    bomb = ["a: &a [x, x, x, x, x, x, x, x, x, x]"]
    for k, prev in zip("bcdefghi", "abcdefgh"):
        bomb.append(f"{k}: &{k} [*{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}]")
    bomb.append("name: *i\njoints: [{a: 0, alpha: 0, d: 0, theta: 0}]")
    f = write(tmp_path / "bomb.yaml", "\n".join(bomb) + "\n")
    # a hang guard, not a speed claim: expanding the aliases would take minutes and gigabytes before any check
    with deadline(60), pytest.raises(RobotSpecError, match="aliases"):
        torchcal.load_robot(f)
    latin = "name: r\u00f6bot\njoints: [{a: 0, alpha: 0, d: 0, theta: 0}]\n".encode("latin-1")
    g = write(tmp_path / "latin.yaml", latin)
    with pytest.raises(RobotSpecError, match="not UTF-8"):
        torchcal.load_robot(g)


def test_oversized_description_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr("torchcal.robot.load.MAX_DESCRIPTION_BYTES", 100)
    with pytest.raises(RobotSpecError, match="larger than a robot description"):
        torchcal.load_robot(urdf(tmp_path))


def damage(run_dir: Path, tmp_path: Path, how: str) -> Path:
    bad = tmp_path / "run"
    shutil.copytree(run_dir, bad)
    if how == "no-model.pt":
        (bad / "model.pt").unlink()
    elif how == "truncated":
        raw = (bad / "model.pt").read_bytes()
        (bad / "model.pt").write_bytes(raw[: len(raw) // 2])
    elif how == "pickle":

        class Payload:
            def __reduce__(self):
                return (print, ("pwned",))

        torch.save({"x": Payload()}, bad / "model.pt")
    elif how in ("no-key", "outside", "not-json"):
        meta = json.loads((bad / "model.json").read_text())
        if how == "no-key":
            del meta["effects"]
        elif how == "outside":
            meta["robot_file"] = "../../../etc/passwd.urdf"
        (bad / "model.json").write_text("{oops" if how == "not-json" else json.dumps(meta))
    return bad


@pytest.mark.parametrize(
    "how, match",
    [
        ("no-model.pt", "model.pt is missing"),
        ("truncated", "model.pt cannot be read"),
        ("pickle", "model.pt"),
        ("no-key", "lacks effects"),
        ("outside", "outside the run directory"),
        ("not-json", "model.json cannot be read"),
    ],
)
def test_damaged_run_directories_are_refused(how, match, run_dir, campaign, tmp_path, capsys):
    bad = damage(run_dir, tmp_path, how)
    assert main(["predict", str(bad), str(campaign / "test.csv"), "--out", str(tmp_path / "p.csv"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "pwned" not in err
    with pytest.raises(OptionError, match=match):
        torchcal.use.rundir.load_model(bad)


def test_unexpected_errors_are_summarised_and_debug_shows_the_traceback(campaign, tmp_path, capsys, monkeypatch):
    def broken(*a, **k):
        raise ZeroDivisionError("something internal")

    monkeypatch.setattr(calibration_module(), "calibrate", broken)
    assert calibrate(campaign / "train.csv", tmp_path / "o") == 1
    err = capsys.readouterr().err
    assert "internal error: ZeroDivisionError: something internal" in err and "please report" in err
    assert "Traceback" not in err
    assert (
        main(
            [
                "--debug",
                "calibrate",
                str(campaign / "train.csv"),
                "--robot",
                "ur5",
                "--out",
                str(tmp_path / "o"),
                "--quiet",
            ]
        )
        == 1
    )
    assert "Traceback" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "opt",
    [
        ["--joint-noise", "nan"],
        ["--joint-noise", "-1"],
        ["--tracker-noise", "0"],
        ["--tracker-noise", "inf"],
        ["--rank-tol", "-1"],
        ["--rank-tol", "0"],
        ["--holdout", "1.5"],
        ["--holdout", "0"],
    ],
)
def test_options_are_validated_up_front(opt, campaign, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        calibrate(campaign / "train.csv", tmp_path / "o", *opt)
    assert e.value.code == 2 and opt[0] in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_simulate_options_are_validated(tmp_path):
    for opt in (["--poses", "0"], ["--joint-noise", "nan"], ["--tracker-noise", "-1"]):
        with pytest.raises(SystemExit):
            main(["simulate", "--robot", "ur5", "--out", str(tmp_path / "s"), *opt])
    assert cli_simulate(tmp_path / "s", "--trajectory", "--samples", "50", "--train-samples", "60") == 2


def test_report_json_is_strict_json(run_dir):
    def refuse(c):
        raise AssertionError(f"non-standard JSON constant {c}")

    json.loads((run_dir / "report.json").read_text(), parse_constant=refuse)


def test_header_robot_that_disagrees_with_robot_is_an_error(campaign, tmp_path, capsys):
    text = (campaign / "train.csv").read_text()
    assert "# robot: ur5" in text
    f = write(tmp_path / "ur10.csv", text.replace("# robot: ur5", "# robot: ur10"))
    assert calibrate(f, tmp_path / "o") == 2
    assert "names another robot than --robot ur5" in capsys.readouterr().err


def test_predict_refuses_data_of_another_robot(run_dir, campaign, tmp_path, capsys):
    text = (campaign / "test.csv").read_text().replace("# robot: ur5", "# robot: panda")
    f = write(tmp_path / "panda.csv", text)
    assert main(["predict", str(run_dir), str(f), "--out", str(tmp_path / "p.csv"), "--quiet"]) == 2
    assert "names another robot than the run's robot robot/ur5.yaml" in capsys.readouterr().err


def test_simulate_without_line_of_sight_names_real_options(tmp_path, capsys):
    assert (
        main(
            [
                "simulate",
                "--robot",
                "ur5.urdf",
                "--base-link",
                "wrist_2_link",
                "--out",
                str(tmp_path / "s"),
                "--poses",
                "20",
                "--quiet",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "line-of-sight" in err and "--base-link" in err and "Traceback" not in err


# --------------------------------------------------------------------------- item 8: promises kept


def test_ekf_trainer_at_top_level():
    from torchcal.filter import EKFTrainer

    assert torchcal.EKFTrainer is EKFTrainer and "EKFTrainer" in torchcal.__all__


def test_correction_net_is_float64_only():
    with pytest.raises(ShapeError, match="float64"):
        torchcal.CorrectionNet(6, 29, dtype=torch.float32)
    net = torchcal.CorrectionNet(6, 29, seed=0)
    with pytest.raises(ShapeError, match="torch.float32.*torch.float64"):
        net(torch.zeros(2, 6, dtype=torch.float32))
    assert net(torch.zeros(2, 6, dtype=torch.float64)).dtype == torch.float64


def test_float32_joints_to_the_robot_name_both_dtypes():
    robot = torchcal.load_robot("ur5")
    with pytest.raises(ShapeError, match="torch.float32.*torch.float64"):
        robot(torch.zeros(1, 6, dtype=torch.float32))


def test_continuous_joint_past_one_turn_is_accepted(tmp_path):
    f = urdf(tmp_path)
    f.write_text(f.read_text().replace('name="j1" type="revolute"', 'name="j1" type="continuous"'))
    robot = torchcal.load_robot(f)
    data = write(tmp_path / "d.csv", "q1,q2,x,y,z\n7.5,0.1,0.1,0.2,0.3\n-9.0,0.2,0.1,0.2,0.3\n")
    m = torchcal.read_measurements(data, dof=2, joint_limits=robot.limits)
    assert m.q[0, 0].item() == 7.5
    bad = write(tmp_path / "e.csv", "q1,q2,x,y,z\n0.1,7.5,0.1,0.2,0.3\n")  # j2 is bounded: still degrees-like
    with pytest.raises(MeasurementFileError, match="look like degrees"):
        torchcal.read_measurements(bad, dof=2, joint_limits=robot.limits)


def test_help_cites_no_outside_document():
    """No help text (the command's or any subcommand's) cites a document users do not have."""
    parser = torchcal.cli.build_parser()
    commands = parser._subparsers._group_actions[0].choices
    assert {"simulate", "calibrate", "predict", "compensate", "convert", "demo"} <= set(commands)
    for text in [parser.format_help()] + [sub.format_help() for sub in commands.values()]:
        assert "CONTRACT" not in text and "§" not in text and "progress bar" not in text
