"""Hostile inputs, round 4 (issue 35's last item): what this round adds, the importer (``convert --map``), the 6-D
``compensate``, ``export`` and ``fleet``.

Every case is a clear refusal (exit 2, naming the file, line, column or option, nothing written, no foreign file
changed) or a correct result; never exit 1, never a hang. One tiny calibrated run (60 UR5 poses with orientation,
kinematic) is shared by the module.
"""

import json
import math

import pytest
from _cli import cli_simulate, refuse, run_cli, snapshot

from torchcal import fleet as F
from torchcal.cli import main

Q6 = [f"q{k}" for k in range(1, 7)]


@pytest.fixture(scope="module")
def oriented(tmp_path_factory):
    """60 simulated UR5 poses with the probe's orientation, and their kinematic run."""
    root = tmp_path_factory.mktemp("oriented")
    assert cli_simulate(root / "sim", "--poses", "60", "--test-poses", "5", "--orientation", "0.01", "--seed", "3") == 0
    run = root / "cal"
    cmd = ["calibrate", str(root / "sim" / "train.csv"), "--robot", "ur5", "--method", "kinematic"]
    assert main([*cmd, "--out", str(run), "--quiet"]) == 0
    return root


def _rows(path):
    lines = [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    header = lines[0].split(",")
    return header, [dict(zip(header, ln.split(","), strict=True)) for ln in lines[1:]]


# ----------------------------------------------------------------------------------- the importer (convert --map)

JOINTS = "0 -90 90 0 90 0\n10 -80 85 5 90 0\n20 -70 80 10 85 5\n"
POINTS = "812.1 -191.5 425.0\n790.3 -50.2 520.7\n700.9 90.4 610.2\n"
MAP = (
    "read: {delimiter: whitespace, header: false}\nunits: {length: mm, angle: deg}\n"
    "joints: {input: 1, columns: 1-6}\nposition: {input: 2, columns: 1-3}\n"
)


def _convert(tmp_path, map_text, joints=JOINTS, points=POINTS, extra=()):
    (tmp_path / "in").mkdir(exist_ok=True)
    (tmp_path / "in" / "map.yaml").write_text(map_text)
    (tmp_path / "in" / "joints.txt").write_text(joints)
    files = [tmp_path / "in" / "joints.txt"]
    if points is not None:
        (tmp_path / "in" / "points.txt").write_text(points)
        files.append(tmp_path / "in" / "points.txt")
    files += list(extra)
    return ["convert", "--map", str(tmp_path / "in" / "map.yaml"), *map(str, files), "--out", str(tmp_path / "o.csv")]


def test_the_map_that_works_writes_the_rows(tmp_path):
    """The reference's own example, as a control for the refusals below."""
    assert run_cli(_convert(tmp_path, MAP)) == 0
    header, rows = _rows(tmp_path / "o.csv")
    assert len(rows) == 3 and float(rows[1]["q1"]) == pytest.approx(math.radians(10))
    assert float(rows[0]["x"]) == pytest.approx(0.8121)


def test_map_unknown_key(tmp_path, capsys):
    refuse(capsys, tmp_path, _convert(tmp_path, MAP + "postion: {columns: 1-3}\n"), "map.yaml", "postion")


def test_map_key_of_the_wrong_type(tmp_path, capsys):
    bad = MAP.replace("units: {length: mm, angle: deg}", "units: mm")
    refuse(capsys, tmp_path, _convert(tmp_path, bad), "map.yaml", "units")


def test_map_column_beyond_the_file(tmp_path, capsys):
    bad = MAP.replace("columns: 1-3", "columns: 2-4")
    refuse(capsys, tmp_path, _convert(tmp_path, bad), "points.txt", "4")


def test_map_yaml_alias_bomb_is_refused_quickly(tmp_path, capsys):
    """Nine levels of nine aliases (9**9 cells once expanded) under a key the MAP knows."""
    bomb = "extra:\n  a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]\n"
    for k in "bcdefghi":
        prev = chr(ord(k) - 1)
        bomb += f"  {k}: &{k} [{', '.join([f'*{prev}'] * 9)}]\n"
    refuse(capsys, tmp_path, _convert(tmp_path, MAP + bomb), "map.yaml", seconds=20)


def test_map_huge_file_is_refused_by_its_size(tmp_path, capsys):
    """A 'MAP' of 30 MB (a data file given as the MAP by mistake) is refused before it is parsed."""
    huge = MAP + "# " + "x" * (30 * 2**20) + "\n"
    refuse(capsys, tmp_path, _convert(tmp_path, huge), "map.yaml", seconds=20)


QUAT_MAP = (
    "read: {delimiter: whitespace, header: false}\nunits: {length: mm, angle: deg}\n"
    "joints: {input: 1, columns: 1-6}\nposition: {input: 2, columns: 1-3}\nquaternion: {input: 2, columns: 4-7}\n"
)


def test_quaternion_of_zero_norm(tmp_path, capsys):
    pts = "812.1 -191.5 425.0 1 0 0 0\n790.3 -50.2 520.7 0 0 0 0\n700.9 90.4 610.2 0 1 0 0\n"
    refuse(capsys, tmp_path, _convert(tmp_path, QUAT_MAP, points=pts), "points.txt", "line 2")


def test_matrix_that_is_no_rotation(tmp_path, capsys):
    m = "read: {delimiter: whitespace, header: false}\njoints: {input: 1, columns: 1-6}\n"
    m += "matrix: {input: 2, columns: 1-16}\n"
    good = "1 0 0 0.8 0 1 0 0.1 0 0 1 0.4 0 0 0 1"
    skew = "1 0.5 0 0.8 0 1 0 0.1 0 0 1 0.4 0 0 0 1"  # a shear: no rotation
    pts = f"{good}\n{skew}\n{good}\n"
    refuse(capsys, tmp_path, _convert(tmp_path, m, joints=JOINTS, points=pts), "points.txt", "line 2")


def test_units_that_are_neither(tmp_path, capsys):
    bad = MAP.replace("{length: mm, angle: deg}", "{length: inch, angle: deg}")
    refuse(capsys, tmp_path, _convert(tmp_path, bad), "map.yaml", "inch")


@pytest.mark.parametrize("cell", ["nan", "inf"])
def test_nan_or_inf_cell(tmp_path, capsys, cell):
    pts = POINTS.replace("-50.2", cell)
    refuse(capsys, tmp_path, _convert(tmp_path, MAP, points=pts), "points.txt", "line 2")


def test_the_same_probe_named_for_two_files(tmp_path, capsys):
    """Two points files under one probe name would be two readings of one reflector at every pose: refused."""
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "b.txt").write_text(POINTS)
    bad = MAP.replace("position: {input: 2, columns: 1-3}", "position: {input: [2, 3], columns: 1-3}")
    argv = _convert(tmp_path, bad + "probe: [A, A]\n", extra=[tmp_path / "in" / "b.txt"])
    refuse(capsys, tmp_path, argv, "map.yaml", "A")


def test_an_empty_input(tmp_path, capsys):
    refuse(capsys, tmp_path, _convert(tmp_path, MAP, points=""), "points.txt")


def test_rows_that_do_not_pair(tmp_path, capsys):
    refuse(capsys, tmp_path, _convert(tmp_path, MAP, points=POINTS + "1 2 3\n"), "points.txt")


def test_quaternion_order_unknown(tmp_path, capsys):
    bad = QUAT_MAP.replace("columns: 4-7}", "columns: 4-7, order: zyxw}")
    pts = "812.1 -191.5 425.0 1 0 0 0\n790.3 -50.2 520.7 1 0 0 0\n700.9 90.4 610.2 0 1 0 0\n"
    refuse(capsys, tmp_path, _convert(tmp_path, bad, points=pts), "map.yaml", "zyxw")


def test_convert_out_is_an_input(tmp_path, capsys):
    argv = _convert(tmp_path, MAP)
    argv[-1] = str(tmp_path / "in" / "points.txt")
    refuse(capsys, tmp_path, argv, "points.txt")


# ------------------------------------------------------------------------------------------- 6-D compensation


def _targets(oriented, tmp_path, n=3, edit=None):
    """The first n test rows' joints and full poses as a targets file; ``edit(cells)`` spoils a row."""
    header, rows = _rows(oriented / "sim" / "test.csv")
    cols = [*Q6, "x", "y", "z", "rx", "ry", "rz"]
    lines = [",".join(cols)]
    for i, r in enumerate(rows[:n]):
        cells = {c: r[c] for c in cols}
        if edit is not None and i == 1:
            edit(cells)
        lines.append(",".join(cells[c] for c in cols))
    (tmp_path / "t.csv").write_text("\n".join(lines) + "\n")
    return tmp_path / "t.csv"


def _compensate(oriented, targets, tmp_path, *extra):
    return ["compensate", str(oriented / "cal"), str(targets), "--out", str(tmp_path / "j.csv"), *extra]


def test_six_d_targets_reached(oriented, tmp_path):
    """The control: the test rows' own poses are reached, the orientation miss written."""
    assert run_cli(_compensate(oriented, _targets(oriented, tmp_path), tmp_path)) == 0
    header, rows = _rows(tmp_path / "j.csv")
    assert "miss_angle" in header and all(r["status"] == "converged" for r in rows)


def test_six_d_orientation_not_a_rotation_vector(oriented, tmp_path, capsys):
    """A rotation vector of 40 rad is no orientation anyone measured (degrees written as radians, or garbage)."""
    t = _targets(oriented, tmp_path, edit=lambda c: c.update(rx="40.0"))
    refuse(capsys, tmp_path, _compensate(oriented, t, tmp_path), "t.csv", "line 3", "rx")


def test_six_d_orientation_in_degrees_on_a_radian_run(oriented, tmp_path, capsys):
    """Every orientation in degrees (the joints too), without --angle-unit deg: refused, the option named."""

    def deg(c):
        for k in [*Q6, "rx", "ry", "rz"]:
            c[k] = repr(math.degrees(float(c[k])))

    t = _targets(oriented, tmp_path, n=1)
    text = t.read_text().splitlines()
    cells = dict(zip(text[0].split(","), text[1].split(","), strict=True))
    deg(cells)
    cells["rx"], cells["ry"], cells["rz"] = "120.0", "-75.0", "170.0"
    t.write_text(text[0] + "\n" + ",".join(cells[c] for c in text[0].split(",")) + "\n")
    refuse(capsys, tmp_path, _compensate(oriented, t, tmp_path), "t.csv", "--angle-unit")


def test_six_d_nan_orientation(oriented, tmp_path, capsys):
    t = _targets(oriented, tmp_path, edit=lambda c: c.update(ry="nan"))
    refuse(capsys, tmp_path, _compensate(oriented, t, tmp_path), "t.csv", "line 3", "ry")


def test_six_d_partial_orientation(oriented, tmp_path, capsys):
    t = _targets(oriented, tmp_path)
    t.write_text("\n".join(",".join(ln.split(",")[:-1]) for ln in t.read_text().splitlines()) + "\n")  # no rz
    refuse(capsys, tmp_path, _compensate(oriented, t, tmp_path), "t.csv", "rz")


@pytest.mark.parametrize("weight", ["0", "-0.1", "inf", "nan"])
def test_orientation_weight_not_positive_finite(oriented, tmp_path, capsys, weight):
    t = _targets(oriented, tmp_path)
    argv = _compensate(oriented, t, tmp_path, f"--orientation-weight={weight}")
    refuse(capsys, tmp_path, argv, "--orientation-weight")


def test_orientation_targets_with_position_only(oriented, tmp_path, capsys):
    """rx,ry,rz with --position-only: the positions are solved, the orientations kept as written, and it says so."""
    t = _targets(oriented, tmp_path)
    assert run_cli(_compensate(oriented, t, tmp_path, "--position-only")) == 0
    header, rows = _rows(tmp_path / "j.csv")
    assert "miss_angle" not in header and all(r["status"] == "converged" for r in rows)
    assert "# compensation: position only (--position-only)" in (tmp_path / "j.csv").read_text()


def test_compensate_output_fed_back_as_targets(oriented, tmp_path, capsys):
    """compensate's own output as TARGETS (its status column is text): refused at the first such cell."""
    assert run_cli(_compensate(oriented, _targets(oriented, tmp_path), tmp_path)) == 0
    (tmp_path / "j.csv").rename(tmp_path / "out1.csv")
    refuse(capsys, tmp_path, _compensate(oriented, tmp_path / "out1.csv", tmp_path), "out1.csv", "line", "status")


# ------------------------------------------------------------------------------------------------------ export


@pytest.fixture(scope="module")
def seven_joints(tmp_path_factory):
    """A kinematic run of the built-in 7-joint DH arm: no UR."""
    root = tmp_path_factory.mktemp("arm7")
    assert cli_simulate(root / "sim", "--poses", "40", "--test-poses", "3", "--seed", "1", robot="arm7_dh") == 0
    cmd = ["calibrate", str(root / "sim" / "train.csv"), "--robot", "arm7_dh", "--method", "kinematic"]
    assert main([*cmd, "--out", str(root / "cal"), "--quiet"]) == 0
    return root / "cal"


def test_export_ur_ros2_of_a_robot_that_is_no_ur(seven_joints, tmp_path, capsys):
    """ur-ros2 of a 7-joint arm is refused, nothing written, not even the new folder; its DH file is written."""
    argv = ["export", str(seven_joints), "--format", "ur-ros2", "--out", str(tmp_path / "new" / "k.yaml")]
    refuse(capsys, tmp_path, argv, "arm7_dh", "six revolute joints", "7 joints")
    assert run_cli(["export", str(seven_joints), "--format", "dh", "--out", str(tmp_path / "arm7.yaml")]) == 0


def test_export_over_a_foreign_file(oriented, tmp_path, capsys):
    (tmp_path / "kin.yaml").write_text("mine: true\n")
    argv = ["export", str(oriented / "cal"), "--format", "ur-ros2", "--out", str(tmp_path / "kin.yaml")]
    refuse(capsys, tmp_path, argv, "kin.yaml", "--force")


@pytest.mark.parametrize("fmt", ["dh", "urdf"])
def test_export_into_a_missing_directory(oriented, tmp_path, fmt):
    """--out in folders that do not exist yet: made, as predict and plan make theirs (it was an internal error)."""
    out = tmp_path / "no" / "such" / "r.txt"
    assert run_cli(["export", str(oriented / "cal"), "--format", fmt, "--out", str(out)]) == 0
    assert out.read_text().startswith("# written_by: torchcal") or "<robot" in out.read_text()


def test_compensate_and_convert_into_a_missing_directory(oriented, tmp_path):
    """own: compensate and convert refused an --out in folders that do not exist yet, where predict, plan, export
    and simulate make them; now every command makes them (at the end, when the work succeeded)."""
    out = tmp_path / "no" / "such" / "joints.csv"
    assert run_cli(["compensate", str(oriented / "cal"), str(oriented / "sim" / "test.csv"), "--out", str(out)]) == 0
    assert out.is_file()
    (tmp_path / "map.yaml").write_text("joints: 1-6\nposition: 7-9\n", encoding="utf-8")
    out = tmp_path / "new" / "converted.csv"
    argv = ["convert", "--map", str(tmp_path / "map.yaml"), str(oriented / "sim" / "test.csv"), "--out", str(out)]
    assert run_cli(argv) == 0 and out.is_file()


@pytest.mark.parametrize("damage", ["model.pt", "model.json", "robot"])
def test_export_of_a_damaged_run(oriented, tmp_path, capsys, damage):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(oriented / "cal", run)
    target = run / damage
    if target.is_dir():
        shutil.rmtree(target)
    else:
        target.write_bytes(target.read_bytes()[:50])
    argv = ["export", str(run), "--format", "urdf", "--out", str(tmp_path / "r.urdf")]
    refuse(capsys, tmp_path, argv, "run")


def test_export_over_a_file_of_the_run(oriented, tmp_path, capsys):
    before = snapshot(oriented / "cal")
    argv = ["export", str(oriented / "cal"), "--format", "urdf", "--out", str(oriented / "cal" / "report.json")]
    refuse(capsys, tmp_path, argv, "report.json", "input directory")
    assert snapshot(oriented / "cal") == before


def test_export_of_a_folder_that_is_no_run(tmp_path, capsys):
    (tmp_path / "notarun").mkdir()
    argv = ["export", str(tmp_path / "notarun"), "--format", "ur-ros2", "--out", str(tmp_path / "k.yaml")]
    refuse(capsys, tmp_path, argv, "notarun")


def test_export_ur_ros2_round_trip_and_replace_own_file(oriented, tmp_path):
    """The control: the file is written, and written again over itself (torchcal's own) without --force."""
    import yaml

    argv = ["export", str(oriented / "cal"), "--format", "ur-ros2", "--out", str(tmp_path / "k.yaml")]
    assert run_cli(argv) == 0 and run_cli(argv) == 0
    k = yaml.safe_load((tmp_path / "k.yaml").read_text())["kinematics"]
    assert set(k) >= {"shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3"}


# ------------------------------------------------------------------------------------------------------- fleet


def _fleet(tmp_path, text, capsys=None):
    (tmp_path / "m").mkdir(exist_ok=True)
    (tmp_path / "m" / "manifest.csv").write_text(text)
    return ["fleet", str(tmp_path / "m" / "manifest.csv"), "--out", str(tmp_path / "fleet")]


@pytest.fixture()
def serial(monkeypatch):
    monkeypatch.setattr(F, "ray_available", lambda: False)


@pytest.mark.parametrize(
    "text, needles",
    [
        ("name,data,robot\nr1,a.csv,ur5\nr1,b.csv,ur5\n", ("manifest.csv", "line 3", "r1")),
        ("name,data,robot\na/b,a.csv,ur5\n", ("manifest.csv", "line 2", "a/b")),
        ("name,data,robot\n..,a.csv,ur5\n", ("manifest.csv", "line 2", "..")),
        ("name,data,robot\n", ("manifest.csv",)),
        ("", ("manifest.csv",)),
        ("name,data\nr1,a.csv\n", ("manifest.csv", "robot")),
        ("name,data,robot,method\nr1,a.csv,ur5,fast\n", ("manifest.csv", "line 2", "method", "fast")),
        ("name,data,robot\nr1,a.csv\n", ("manifest.csv", "line 2")),
        ("name,data,robot\nreport.json,a.csv,ur5\n", ("manifest.csv", "line 2", "report.json")),
        ("name,data,robot\nr1,,ur5\n", ("manifest.csv", "line 2", "data")),
    ],
    ids=[
        "duplicate",
        "slash",
        "dotdot",
        "header-only",
        "empty",
        "no-robot-column",
        "method",
        "ragged",
        "summary",
        "no-data",
    ],
)
def test_fleet_manifest_refused(tmp_path, capsys, serial, text, needles):
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "a.csv").write_text("q1\n")
    (tmp_path / "m" / "b.csv").write_text("q1\n")
    refuse(capsys, tmp_path, _fleet(tmp_path, text), *needles)


def test_fleet_lines_refused_at_their_task(oriented, tmp_path, serial):
    """A missing data file, a robot that does not exist, a prior that is not a run: each line is reported refused
    with what is wrong named (calibrate's exit 2), none gets a run folder, the command exits 0 with its summary."""
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "notarun").mkdir()
    data = oriented / "sim" / "train.csv"
    text = (
        "name,data,robot,method,prior\ngone,missing.csv,ur5,kinematic,\n"
        f"nobot,{data},no_such_robot,kinematic,\nnoprior,{data},ur5,kinematic,notarun\n"
    )
    assert run_cli(_fleet(tmp_path, text)) == 0
    d = json.loads((tmp_path / "fleet" / "report.json").read_text())
    errors = {r["name"]: r["error"] for r in d["robots"] if r["status"] == "refused"}
    assert "missing.csv" in errors["gone"] and "no_such_robot" in errors["nobot"]
    assert "notarun" in errors["noprior"] and "not a torchcal run" in errors["noprior"]
    assert d["n_ok"] == 0 and sorted(p.name for p in (tmp_path / "fleet").iterdir()) == [
        ".torchcal-run",
        "report.json",
        "report.md",
    ]
