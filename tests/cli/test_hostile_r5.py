"""Hostile inputs, round 5 (issue 47): the simulator's own output at joint limits, devices and FIFOs given as any path,
``convert``'s silent wrong results, misleading messages and the layouts the importer could not express.

Every case is a clear refusal (exit 2, naming the file, line, column or option, nothing written) or a correct
result; never exit 1, never a hang.
"""

import math

import pytest
import torch
from _cli import cli_simulate, deadline, refuse, refused, run_cli, snapshot

from torchcal.cli import main
from torchcal.data.measurements import MeasurementFileError, read_measurements
from torchcal.robot.load import load_robot

# ------------------------------------------------------------------------------- 1: the simulator at joint limits


def test_simulated_panda_at_its_limits_is_read_back(tmp_path):
    """Issue 47 item 1: joint noise put line 93's q2 3.9e-6 rad past panda's limit, and calibrate refused it."""
    assert cli_simulate(tmp_path / "s", "--seed", "13", "--poses", "150", "--test-poses", "20", robot="panda") == 0
    robot = load_robot("panda")
    for part in ("train.csv", "test.csv"):
        m = read_measurements(tmp_path / "s" / part, dof=robot.dof, joint_limits=robot.limits, robot_name="panda")
        assert bool((m.q >= robot.limits[:, 0]).all() and (m.q <= robot.limits[:, 1]).all())


def test_a_limit_message_shows_the_excess(tmp_path):
    """A reading 3.9e-6 rad past a limit printed with six digits looked equal to the limit."""
    robot = load_robot("panda")
    lo = robot.limits[1, 0].item()
    q = [0.0, lo - 3.9e-6, 0.0, -1.5, 0.0, 1.5, 0.0]
    (tmp_path / "d.csv").write_text("q1,q2,q3,q4,q5,q6,q7,x,y,z\n" + ",".join(map(repr, q)) + ",1,0,0\n")
    with pytest.raises(MeasurementFileError) as info:
        read_measurements(tmp_path / "d.csv", dof=7, joint_limits=robot.limits, robot_name="panda")
    msg = str(info.value)
    assert f"{lo - 3.9e-6:.12g}" in msg and "3.9e-06 rad below" in msg, msg


def test_a_limit_message_in_degrees_shows_the_excess_in_both(tmp_path):
    robot = load_robot("panda")
    hi = robot.limits[0, 1].item()
    q = [hi + 1e-5, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0]
    row = ",".join(repr(math.degrees(v)) for v in q)
    (tmp_path / "d.csv").write_text("q1,q2,q3,q4,q5,q6,q7,x,y,z\n" + row + ",1,0,0\n")
    with pytest.raises(MeasurementFileError) as info:
        read_measurements(tmp_path / "d.csv", dof=7, joint_limits=robot.limits, robot_name="panda", angle_unit="deg")
    assert "1e-05 rad) above" in str(info.value) and "0.000573 deg" in str(info.value), str(info.value)


# ---------------------------------------------------------------- 2: a device, FIFO or directory as any path argument

MAP = (
    "read: {delimiter: whitespace, header: false}\nunits: {length: mm, angle: deg}\n"
    "joints: {input: 1, columns: 1-6}\nposition: {input: 2, columns: 1-3}\n"
)
JOINTS = "0 -90 90 0 90 0\n10 -80 85 5 90 0\n20 -70 80 10 85 5\n"
POINTS = "812.1 -191.5 425.0\n790.3 -50.2 520.7\n700.9 90.4 610.2\n"


@pytest.fixture
def odd(tmp_path):
    """A FIFO, a character device and a directory, by name, beside good convert inputs (all outside ``tmp_path/w``,
    where the commands write)."""
    import os

    base = tmp_path / "odd"
    base.mkdir()
    os.mkfifo(base / "fifo.csv")
    (base / "dir.csv").mkdir()
    (base / "map.yaml").write_text(MAP)
    (base / "j.txt").write_text(JOINTS)
    (base / "p.txt").write_text(POINTS)
    (tmp_path / "w").mkdir()
    return (
        {
            "fifo": (base / "fifo.csv", "FIFO"),
            "device": ("/dev/zero", "character device"),
            "dir": (base / "dir.csv", "directory"),
        },
        base,
        tmp_path / "w",
    )


FILE_ARGS = {
    "calibrate DATA": lambda b, c, r, w: ["calibrate", b, "--robot", "ur5", "--out", f"{w}/o"],
    "predict DATA": lambda b, c, r, w: ["predict", str(r), b, "--out", f"{w}/o.csv"],
    "compensate TARGETS": lambda b, c, r, w: ["compensate", str(r), b, "--out", f"{w}/o.csv"],
    "station POINTS": lambda b, c, r, w: ["station", str(r), b, "--out", f"{w}/o"],
    "plan --candidates": lambda b, c, r, w: ["plan", "--run", str(r), "--candidates", b, "--n", "5", "--out", f"{w}/o"],
    "fleet MANIFEST": lambda b, c, r, w: ["fleet", b, "--out", f"{w}/o"],
    "convert --map": lambda b, c, r, w: ["convert", "--map", b, f"{c}/j.txt", f"{c}/p.txt", "--out", f"{w}/o.csv"],
    "convert INPUT": lambda b, c, r, w: ["convert", "--map", f"{c}/map.yaml", f"{c}/j.txt", b, "--out", f"{w}/o.csv"],
}


@pytest.mark.parametrize("what", ["fifo", "device", "dir"])
@pytest.mark.parametrize("arg", list(FILE_ARGS))
def test_a_file_argument_that_is_no_file(odd, run_dir, capsys, arg, what):
    """Issue 47 item 2: ``fleet /dev/zero`` grew to 19.8 GB, ``convert --map /dev/zero`` to 2.2 GB, a FIFO blocked;
    a directory was 'no such file'. Every file argument is refused at once, saying what the path is."""
    kinds, base, work = odd
    bad, kind = kinds[what]
    before = snapshot(work)
    assert run_cli(FILE_ARGS[arg](str(bad), base, run_dir, work), seconds=20) == 2
    err = refused(capsys, str(bad), kind)
    assert "no such file" not in err.lower(), err
    assert snapshot(work) == before


# --------------------------------------------------------------------------- 6: convert's silent wrong results


def _convert(tmp_path, map_text, joints=JOINTS, points=POINTS, extra=(), inputs=None):
    """``convert --map`` of files written under ``tmp_path/in``; ``inputs`` replaces the INPUT list."""
    (tmp_path / "in").mkdir(exist_ok=True)
    (tmp_path / "in" / "map.yaml").write_text(map_text)
    (tmp_path / "in" / "joints.txt").write_text(joints)
    (tmp_path / "in" / "points.txt").write_text(points)
    files = inputs or [tmp_path / "in" / "joints.txt", tmp_path / "in" / "points.txt", *extra]
    return ["convert", "--map", str(tmp_path / "in" / "map.yaml"), *map(str, files), "--out", str(tmp_path / "o.csv")]


TWO = MAP.replace("position: {input: 2, columns: 1-3}", "position: {input: [2, 3], columns: 1-3}\nprobe: [A, B]")


def test_the_same_points_file_twice(tmp_path, capsys):
    """It became two probes of identical rows, and calibrate's sigmas came out 1/sqrt(2) too small."""
    argv = _convert(tmp_path, TWO)
    argv.insert(5, argv[4])  # joints.txt points.txt points.txt
    refuse(capsys, tmp_path, argv, "points.txt", "INPUTs 2 and 3 are the same file")


def test_a_copy_of_the_points_file(tmp_path, capsys):
    (tmp_path / "copy.txt").write_text(POINTS)
    refuse(capsys, tmp_path, _convert(tmp_path, TWO, extra=[tmp_path / "copy.txt"]), "copy.txt", "INPUT 2")


def test_one_input_listed_twice_in_a_role(tmp_path, capsys):
    bad = MAP.replace("position: {input: 2, columns: 1-3}", "position: {input: [2, 2], columns: 1-3}\nprobe: [A, B]")
    refuse(capsys, tmp_path, _convert(tmp_path, bad), "map.yaml", "input 2 twice")


def test_a_map_key_given_twice(tmp_path, capsys):
    """The last 'joints:' won: the first's signs and offsets were dropped (q2 off by 7.7 rad), exit 0."""
    bad = MAP.replace(
        "joints: {input: 1, columns: 1-6}", "joints: {input: 1, columns: 1-6, offset: [0, 90, 0, 0, 0, 0]}"
    )
    bad += "joints: {input: 1, columns: 1-6}\n"
    refuse(capsys, tmp_path, _convert(tmp_path, bad), "map.yaml", "'joints' appears twice", "line 5")


def test_a_nested_map_key_given_twice(tmp_path, capsys):
    bad = MAP.replace("{length: mm, angle: deg}", "{length: mm, angle: deg, length: m}")
    refuse(capsys, tmp_path, _convert(tmp_path, bad), "map.yaml", "'length' appears twice")


@pytest.mark.parametrize("cell", ["0_1", "\u0668\u0661\u0662.\u0661"])  # an underscore; Arabic-Indic 812.1
def test_cells_calibrate_would_refuse_as_numbers(tmp_path, capsys, cell):
    pts = POINTS.replace("812.1", cell)
    refuse(capsys, tmp_path, _convert(tmp_path, MAP, points=pts), "points.txt", "line 1", "not a finite number")


def test_degrees_read_as_radians_name_the_maps_units(tmp_path, capsys):
    bad = MAP.replace("{length: mm, angle: deg}", "{length: mm}")
    refuse(capsys, tmp_path, _convert(tmp_path, bad), "joints.txt", "look like degrees", "units: {angle: deg}")


def test_radians_declared_as_degrees_name_the_maps_units(tmp_path, capsys):
    rad = "".join(" ".join(f"{math.radians(float(v)):.6f}" for v in ln.split()) + "\n" for ln in JOINTS.splitlines())
    refuse(capsys, tmp_path, _convert(tmp_path, MAP, joints=rad), "joints.txt", "look like radians", "units:")


def test_millimetres_read_as_metres_name_the_maps_units(tmp_path, capsys):
    bad = MAP.replace("{length: mm, angle: deg}", "{angle: deg}")
    refuse(capsys, tmp_path, _convert(tmp_path, bad), "map.yaml", "look like millimetres", "units: {length: mm}")


def test_metres_read_as_millimetres_name_the_maps_units(tmp_path, capsys):
    pts = "".join(" ".join(f"{float(v) / 1000:.6f}" for v in ln.split()) + "\n" for ln in POINTS.splitlines())
    refuse(capsys, tmp_path, _convert(tmp_path, MAP, points=pts), "map.yaml", "look like metres", "units: {length: m}")


# ------------------------------------------------------------------------------------------ 7: misleading messages

Q6 = [f"q{k}" for k in range(1, 7)]


def _rows(path):
    lines = [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    header = lines[0].split(",")
    return header, [dict(zip(header, ln.split(","), strict=True)) for ln in lines[1:]]


@pytest.fixture(scope="module")
def oriented(tmp_path_factory):
    """40 simulated UR5 poses with the probe's orientation (and 40 test poses), and their kinematic run."""
    root = tmp_path_factory.mktemp("oriented")
    assert (
        cli_simulate(root / "sim", "--poses", "40", "--test-poses", "40", "--orientation", "0.01", "--seed", "3") == 0
    )
    cmd = ["calibrate", str(root / "sim" / "train.csv"), "--robot", "ur5", "--method", "kinematic"]
    assert main([*cmd, "--out", str(root / "cal"), "--quiet"]) == 0
    return root


def _targets(oriented, tmp_path):
    header, rows = _rows(oriented / "sim" / "test.csv")
    cols = [*Q6, "x", "y", "z", "rx", "ry", "rz"]
    text = ",".join(cols) + "\n" + "".join(",".join(r[c] for c in cols) + "\n" for r in rows)
    (tmp_path / "t.csv").write_text(text)
    return tmp_path / "t.csv"


def test_a_heavy_orientation_weight_converges_as_the_default(oriented, tmp_path, capsys):
    """``--orientation-weight 1e6`` (allowed) marked 0 of 40 rows converged, each 'unreachable, misses by 0.0000 mm
    and 0.0000 deg' (1000: one row): the damped steps drowned the position rows. Now every weight converges where the
    default does (39 of these 40 rows), and a miss is printed with its digits."""
    t = _targets(oriented, tmp_path)
    status = {}
    for weight in ("0.1", "1000", "1e6"):
        argv = ["compensate", str(oriented / "cal"), str(t), "--out", str(tmp_path / f"j{weight}.csv")]
        assert run_cli([*argv, "--orientation-weight", weight], seconds=120) == 0
        status[weight] = [r["status"] for r in _rows(tmp_path / f"j{weight}.csv")[1]]
    assert status["0.1"].count("converged") >= 38
    assert status["1000"] == status["1e6"] == status["0.1"], status
    assert "0.0000 mm" not in capsys.readouterr().err


def test_a_matrix_range_off_by_one_says_so(tmp_path, capsys):
    """An off-by-one ``matrix:`` range was called 'a matrix written column-major?'."""
    m = "read: {delimiter: whitespace, header: false}\nunits: {angle: deg}\njoints: {input: 1, columns: 1-6}\n"
    m += "matrix: {input: 2, columns: 2-17}\n"
    pose = "1 0 0 0.8 0 1 0 0.1 0 0 1 0.4 0 0 0 1"
    pts = f"{pose} 7\n" * 3  # the pose in columns 1-16, a trailing column; the MAP says 2-17
    err = refuse(capsys, tmp_path, _convert(tmp_path, m, points=pts), "points.txt")
    assert "off by 1" in err and "1-16" in err and "column-major" not in err, err


def test_a_matrix_written_column_major_still_says_so(tmp_path, capsys):
    m = "read: {delimiter: whitespace, header: false}\njoints: {input: 1, columns: 1-6}\n"
    m += "matrix: {input: 2, columns: 1-16}\n"
    pose = "1 0 0 0 0 1 0 0 0 0 1 0 0.8 0.1 0.4 1"
    err = refuse(capsys, tmp_path, _convert(tmp_path, m, points=f"{pose}\n" * 3), "points.txt", "column-major")
    assert "off by" not in err


def test_export_ur_ros2_of_a_readings_robot_names_the_readings(tmp_path):
    """It said 'needs six revolute joints, this one has 6 joints (revolute x 6)'."""
    from pathlib import Path

    from torchcal.errors import RobotSpecError
    from torchcal.robot.export_formats import ur_chain_origins

    text = (Path(__file__).parents[1] / "robot" / "data" / "fanuc_like.yaml").read_text()
    five = "[[1,0,0,0,0], [0,1,0,0,0], [0,-1,-1,0,0], [0,0,0,-1,0], [0,0,0,0,-1], [0,0,0,0,-1]]"
    lines = []
    for ln in text.splitlines():
        key = ln.strip().split(":")[0]
        if key == "coupling":
            ln = f"  coupling: {five}"
        elif key in ("lower", "upper"):
            ln = ln.rsplit(",", 1)[0] + "]"  # five readings' limits
        lines.append(ln)
    (tmp_path / "r.yaml").write_text("\n".join(lines) + "\n")
    robot = load_robot(tmp_path / "r.yaml")
    assert robot.dof == 5
    with pytest.raises(RobotSpecError) as info:
        ur_chain_origins(robot)
    assert "driven by 5 controller readings" in str(info.value), str(info.value)


def _full_disk_copy(src, dst, *args, **kwargs):
    """What ``shutil``'s sendfile copy raises on a full disk: the source as ``filename``, the target ``filename2``."""
    import errno
    import os

    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(src), None, str(dst))


def _full_disk(*_args, **_kwargs):
    import errno
    import os

    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_station_on_a_full_disk_names_its_output(oriented, tmp_path, monkeypatch, capsys):
    """It named the input run's report.json as the file it could not write."""
    import torchcal.report.station as S

    monkeypatch.setattr(S.shutil, "copy2", _full_disk_copy)
    _, rows = _rows(oriented / "sim" / "test.csv")
    pts = "".join(",".join(r[c] for c in [*Q6, "x", "y", "z"]) + "\n" for r in rows[:6])
    (tmp_path / "p.csv").write_text(",".join([*Q6, "x", "y", "z"]) + "\n" + pts)
    err = refuse(
        capsys,
        tmp_path,
        ["station", str(oriented / "cal"), str(tmp_path / "p.csv"), "--out", str(tmp_path / "st")],
        f"{tmp_path / 'st'}: No space left on device",
    )
    assert "report.json" not in err


@pytest.mark.parametrize("command", ["compensate", "export"])
def test_a_full_disk_names_the_output(oriented, tmp_path, monkeypatch, capsys, command):
    """'cannot write No space left on device' named no file."""
    import os

    out = tmp_path / "o.yaml"
    if command == "compensate":
        argv = ["compensate", str(oriented / "cal"), str(_targets(oriented, tmp_path)), "--out", str(out)]
    else:
        argv = ["export", str(oriented / "cal"), "--format", "dh", "--out", str(out)]
    monkeypatch.setattr(os, "replace", _full_disk)
    refuse(capsys, tmp_path, argv, f"{out}: No space left on device", seconds=120)


# ------------------------------------------------------------------------------ 9: matrix: makes the fit 6-D


@pytest.mark.parametrize(
    "role, fix",
    [
        ("matrix: {input: 2, columns: 1-16}", "position: {input: 2, columns: [4, 8, 12]}"),
        ("position: {input: 2, columns: 1-3}\nquaternion: {input: 2, columns: 4-7}", "leave out 'quaternion:'"),
    ],
)
def test_convert_says_an_orientation_makes_the_fit_6d(tmp_path, capsys, role, fix):
    """A 4x4 pose in the MAP made every later fit 6-D (3.3x the CPU of a position fit) without a word."""
    m = "read: {delimiter: whitespace, header: false}\nunits: {angle: deg}\njoints: {input: 1, columns: 1-6}\n"
    pts = "1 0 0 0.8 0 1 0 0.1 0 0 1 0.4 0 0 0 1\n" if "matrix" in role else "0.8 0.1 0.4 1 0 0 0\n"
    argv = _convert(tmp_path, m + role + "\n", points=pts * 3)
    with deadline(60):
        assert main(argv) == 0
    err = capsys.readouterr().err
    assert "q1..q6, x, y, z, rx, ry, rz" in err and "6-D" in err and fix in err, err


def test_convert_of_positions_alone_names_no_orientation(tmp_path, capsys):
    with deadline(60):
        assert main(_convert(tmp_path, MAP)) == 0
    err = capsys.readouterr().err
    assert "columns q1..q6, x, y, z" in err and "6-D" not in err and "rx" not in err, err


# ------------------------------------------------------------------- 8: layouts convert --map could not express


def test_several_reflectors_in_one_row(tmp_path):
    """A FANUC campaign: three SMRs in columns 7-15 of each row were 'position.columns names 9 columns, 3
    expected' (three MAPs and hand concatenation). Each triple is one probe's rows now."""
    m = "read: {delimiter: whitespace, header: false}\nunits: {length: mm, angle: deg}\n"
    m += "joints: {columns: 1-6}\nposition: {columns: 7-15}\nprobe: [A, B, C]\n"
    rows = [ln.split() + [f"{800 + 10 * k + i}" for k in range(3) for i in range(3)] for ln in JOINTS.splitlines()]
    (tmp_path / "one.txt").write_text("".join(" ".join(r) + "\n" for r in rows))
    argv = _convert(tmp_path, m, inputs=[tmp_path / "one.txt"])
    assert run_cli(argv) == 0
    got = read_measurements(tmp_path / "o.csv")
    assert got.n == 9 and got.probe_names == ("A", "B", "C")
    assert got.p[got.probe == 1][0].tolist() == pytest.approx([0.810, 0.811, 0.812])
    assert got.q[got.probe == 2][1].tolist() == pytest.approx(got.q[:3][1].tolist())


def test_several_reflectors_with_an_orientation_are_refused(tmp_path, capsys):
    m = "read: {delimiter: whitespace, header: false}\njoints: {columns: 1-6}\nunits: {angle: deg}\n"
    m += "position: {columns: 7-12}\nquaternion: {columns: 13-16}\nprobe: [A, B]\n"
    rows = [ln.split() + ["0.8", "0.1", "0.4", "0.9", "0.1", "0.4", "1", "0", "0", "0"] for ln in JOINTS.splitlines()]
    (tmp_path / "one.txt").write_text("".join(" ".join(r) + "\n" for r in rows))
    refuse(capsys, tmp_path, _convert(tmp_path, m, inputs=[tmp_path / "one.txt"]), "map.yaml", "several reflectors")


def test_predict_ignores_text_columns_beside_the_numbers(campaign, run_dir, tmp_path):
    """Notes beside the numbers in a file given to predict were refused: "'stat' is not a number"."""
    lines = [ln for ln in (campaign / "test.csv").read_text().splitlines() if not ln.startswith("#")]
    text = lines[0] + ",stat,note\n" + "".join(ln + ",ok,pose A\n" for ln in lines[1:])
    (tmp_path / "d.csv").write_text(text)
    plain = tmp_path / "plain.csv"
    plain.write_text("\n".join(lines) + "\n")
    assert run_cli(["predict", str(run_dir), str(tmp_path / "d.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    assert run_cli(["predict", str(run_dir), str(plain), "--out", str(tmp_path / "q.csv")]) == 0
    assert _rows(tmp_path / "p.csv") == _rows(tmp_path / "q.csv")


def test_calibrate_still_refuses_a_text_cell(campaign, tmp_path, capsys):
    lines = [ln for ln in (campaign / "train.csv").read_text().splitlines() if not ln.startswith("#")]
    (tmp_path / "d.csv").write_text(lines[0] + ",stat\n" + "".join(ln + ",ok\n" for ln in lines[1:]))
    argv = ["calibrate", str(tmp_path / "d.csv"), "--robot", "ur5", "--method", "kinematic", "--out", f"{tmp_path}/c"]
    refuse(capsys, tmp_path, argv, "d.csv", "stat", "not a number")


def test_a_singular_fit_names_the_joints_to_check():
    """A wrong joint sign stopped with 'the normal matrix at the solution is singular (rank deficient)' alone."""
    from torchcal.estimate.fit import null_space_hint
    from torchcal.estimate.lm import FitStatus, LMResult

    g = torch.Generator().manual_seed(0)
    J = torch.randn(30, 4, generator=g, dtype=torch.float64)
    J[:, 3] = 2.0 * J[:, 1]  # theta2 and a3 move the probe alike: no fit tells them apart
    res = LMResult(FitStatus.FAILED_SOLVE, 3, torch.zeros(4), [], ["d1", "theta2", "alpha2", "a3"], 30, "", J.T @ J)
    hint = null_space_hint(res)
    assert "theta2, a3" in hint and "(joints 2, 3)" in hint and "signs" in hint, hint
    assert "d1" not in hint and "alpha2" not in hint


# ------------------------------------------------------------------------------------------ 10: leftovers


@pytest.mark.parametrize("fmt", ["dh", "ur-ros2"])
def test_export_into_the_run_directory_is_refused(oriented, tmp_path, capsys, fmt):
    """``export --format dh --out RUN/x.yaml`` wrote a foreign file into the run directory."""
    run = oriented / "cal"
    before = snapshot(run)
    assert run_cli(["export", str(run), "--format", fmt, "--out", str(run / "x.yaml")]) == 2
    refused(capsys, "inside the run directory")
    assert snapshot(run) == before


def test_fleet_reads_every_lines_files_before_any_task(campaign, tmp_path, monkeypatch, capsys):
    """A line whose data calibrate refuses (text in a cell; data of another robot) was told only when its task ran."""
    from torchcal import fleet as F

    monkeypatch.setattr(F, "ray_available", lambda: False)
    lines = (campaign / "train.csv").read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#")) + 1  # the first data row
    lines[k] = "oops," + lines[k].split(",", 1)[1]
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "m.csv").write_text(f"name,data,robot\nA,bad.csv,ur5\nB,{campaign / 'train.csv'},ur10\n")
    assert run_cli(["fleet", str(tmp_path / "m.csv"), "--out", str(tmp_path / "f")], seconds=120) == 0
    err = capsys.readouterr().err
    first = err.index("torchcal fleet: A: refused")
    assert -1 < err.find("m.csv: line 2:") < first and "'oops'" in err[:first], err
    assert -1 < err.find("m.csv: line 3:") < first and "ur10" in err[:first], err


def test_yaml_nested_two_levels(tmp_path):
    """Placements -> column heights -> stationing rows: 'expected a list of rows under solution_spaces'. A dotted
    ``read.rows`` with ``*`` reads every height's rows into its placement's block."""
    joints = [ln.split() for ln in JOINTS.splitlines()]
    points = [ln.split() for ln in POINTS.splitlines()]

    def rows(idx):
        return "".join(f"          - {{q: [{', '.join(joints[i])}], p: [{', '.join(points[i])}]}}\n" for i in idx)

    doc = "placements:\n"
    for place, heights in (("P1", {"h1": [0], "h2": [1]}), ("P2", {"h1": [2]})):
        doc += f"  {place}:\n    solution_spaces:\n"
        for h, idx in heights.items():
            doc += f"      {h}:\n        stationing:\n{rows(idx)}"
    (tmp_path / "campaign.yaml").write_text(doc)
    m = "read: {blocks: placements, rows: solution_spaces.*.stationing}\nunits: {length: mm, angle: deg}\n"
    m += "joints: {columns: q}\nposition: {columns: p}\nstation: {block: placements}\n"
    assert run_cli(_convert(tmp_path, m, inputs=[tmp_path / "campaign.yaml"])) == 0
    got = read_measurements(tmp_path / "o.csv")
    assert got.n == 3 and got.station_names == ("P1", "P2") and got.station.tolist() == [0, 0, 1]
    assert got.p[2].tolist() == pytest.approx([0.7009, 0.0904, 0.6102])
