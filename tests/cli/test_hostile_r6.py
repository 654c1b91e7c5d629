"""Hostile inputs, round 6 (issue 47, "30 new cases of your own"): the surface that round 5 added, the load columns
(``payload``, ``payload_x..z``, ``tau1..tauN``) in the files every command reads and in ``convert --map``'s
``payload:`` and ``torques:``, ``simulate``'s load options, ``export`` (``--geometry cofitted``) and
``check-export RUN FILE``.

Every case is a clear refusal (exit 2, naming the file, line, column or option, nothing written) or a correct
result; never exit 1, never a traceback.
"""

import pytest
from _cli import cli_simulate, refuse, refused, run_cli

# ------------------------------------------------------------------------------ a small campaign with load columns


@pytest.fixture(scope="module")
def loaded(tmp_path_factory):
    """40 simulated UR5 poses (and 10 test poses) at 0 and 5 kg with measured torques, and a kinematic run of them."""
    root = tmp_path_factory.mktemp("loaded")
    assert cli_simulate(root / "s", "--poses", "40", "--test-poses", "10", "--seed", "3", "--payload-levels", "0,5",
                        "--torques") == 0  # fmt: skip
    assert run_cli(["calibrate", str(root / "s" / "train.csv"), "--robot", "ur5", "--method", "kinematic",
                    "--out", str(root / "r")], seconds=120) == 0  # fmt: skip
    return root


def _table(path):
    lines = path.read_text().splitlines()
    comments = [ln for ln in lines if ln.startswith("#")]
    body = [ln.split(",") for ln in lines if ln and not ln.startswith("#")]
    return comments, body[0], body[1:]


def _edited(src, dst, *, cell=None, drop=(), add=()):
    """``src`` written to ``dst`` with the 3rd data row's ``cell=(column, text)`` replaced, columns dropped and
    ``add=((column, text), ..)`` appended to every row. The edited row is line ``len(comments) + 4``."""
    comments, header, rows = _table(src)
    if cell is not None:
        rows[2][header.index(cell[0])] = cell[1]
    keep = [i for i, h in enumerate(header) if h not in drop]
    header = [header[i] for i in keep] + [c for c, _ in add]
    rows = [[r[i] for i in keep] + [v for _, v in add] for r in rows]
    dst.write_text("\n".join([*comments, ",".join(header), *(",".join(r) for r in rows)]) + "\n")
    return len(comments) + 4


# ------------------------------------------------------------- the load columns in calibrate, predict, station


@pytest.mark.parametrize(
    "edit, needles",
    [
        ({"cell": ("payload", "-2")}, ["column 'payload'", ">= 0"]),
        ({"cell": ("payload", "5 kg")}, ["column 'payload'", "'5 kg' is not a number"]),
        ({"cell": ("payload", "5000")}, ["column 'payload'", "kilograms, not grams"]),
        ({"cell": ("tau2", "1e7")}, ["column 'tau2'", "not a joint torque"]),
        ({"cell": ("tau4", "")}, ["column 'tau4'", "empty cell"]),
        ({"drop": ("tau4",)}, ["line", "column 'tau5'", "without gaps"]),
        ({"add": (("tau7", "0"),)}, ["column 'tau7'", "7 torque columns"]),
        ({"add": (("tau07", "0"),)}, ["column 'tau07'", "leading zeros"]),
        ({"add": (("payload_x", "0.1"),)}, ["column 'payload_y'", "needs all of payload_x, payload_y, payload_z"]),
        (
            {"add": (("payload_x", "0"), ("payload_y", "0"), ("payload_z", "12"))},
            ["column 'payload_z'", "beyond 5 m"],
        ),
    ],
    ids=[
        "negative",
        "text",
        "grams",
        "huge-torque",
        "empty-torque",
        "torque-gap",
        "tau7",
        "tau07",
        "com-part",
        "com-far",
    ],  # fmt: skip
)
@pytest.mark.parametrize("command", ["calibrate", "predict", "station"])
def test_a_bad_load_column(loaded, tmp_path, capsys, command, edit, needles):
    """Each refusal names the file, the line (where a row is at fault) and the column, in every command that reads
    the load columns."""
    line = _edited(loaded / "s" / "train.csv", tmp_path / "bad.csv", **edit)
    out = tmp_path / "o"
    argv = {
        "calibrate": ["calibrate", str(tmp_path / "bad.csv"), "--robot", "ur5", "--method", "kinematic"],
        "predict": ["predict", str(loaded / "r"), str(tmp_path / "bad.csv")],
        "station": ["station", str(loaded / "r"), str(tmp_path / "bad.csv")],
    }[command] + ["--out", str(out)]
    if "cell" in edit:
        needles = [*needles, f"line {line}"]
    refuse(capsys, tmp_path, argv, "bad.csv", *needles)


def test_compensate_payload_in_grams(loaded, tmp_path, capsys):
    """``--payload 5000`` (grams for 5 kg) was solved with 5 t at the flange, exit 0; the column refuses it."""
    argv = ["compensate", str(loaded / "r"), str(loaded / "s" / "test.csv"), "--payload", "5000"]
    refuse(capsys, tmp_path, [*argv, "--out", str(tmp_path / "c.csv")], "--payload", "3000")


def test_compensate_targets_with_a_negative_payload(loaded, tmp_path, capsys):
    line = _edited(loaded / "s" / "test.csv", tmp_path / "t.csv", cell=("payload", "-5"))
    argv = ["compensate", str(loaded / "r"), str(tmp_path / "t.csv"), "--out", str(tmp_path / "c.csv")]
    assert run_cli(argv) == 2
    refused(capsys, "t.csv", f"line {line}", "column 'payload'")
    assert not (tmp_path / "c.csv").exists()


def test_predict_keeps_the_load_columns(loaded, tmp_path):
    """A correct result: predict copies the payload and torques of each row through, in order."""
    argv = ["predict", str(loaded / "r"), str(loaded / "s" / "test.csv"), "--out", str(tmp_path / "p.csv")]
    assert run_cli(argv) == 0
    _, h_in, rows_in = _table(loaded / "s" / "test.csv")
    _, h_out, rows_out = _table(tmp_path / "p.csv")
    for col in ("payload", "tau1", "tau6"):
        assert [float(r[h_out.index(col)]) for r in rows_out] == [float(r[h_in.index(col)]) for r in rows_in], col


# ------------------------------------------------------------------------------------------ simulate's loads

SIM = ["simulate", "--robot", "ur5", "--poses", "20", "--test-poses", "5", "--seed", "1"]


@pytest.mark.parametrize(
    "options, option",
    [
        (["--payload", "5000"], "--payload"),
        (["--test-payload", "1e9"], "--test-payload"),
        (["--payload-levels", "0,1e9"], "--payload-levels"),
        (["--torques", "--torque-noise", "1e9"], "--torque-noise"),
    ],
)
def test_simulate_names_the_option_out_of_range(tmp_path, capsys, options, option):
    """The refusal named the configuration's field ('payload_levels', 'sigma_torque'), not the option given."""
    err = refuse(capsys, tmp_path, [*SIM, "--out", str(tmp_path / "s"), *options], option)
    assert "sigma_torque" not in err and "payload_levels" not in err and "test_payload " not in err, err


def test_simulate_payload_and_levels_together(tmp_path, capsys):
    """``--payload 3 --payload-levels 5`` wrote 5 kg rows: --payload was dropped without a word."""
    argv = [*SIM, "--out", str(tmp_path / "s"), "--payload", "3", "--payload-levels", "5"]
    refuse(capsys, tmp_path, argv, "--payload", "--payload-levels")


def test_simulate_torque_noise_without_torques(tmp_path, capsys):
    """``--torque-noise 2`` without ``--torques`` wrote no torques and said nothing."""
    refuse(capsys, tmp_path, [*SIM, "--out", str(tmp_path / "s"), "--torque-noise", "2"], "--torque-noise", "--torques")


def test_simulate_loads_with_several_stations_names_the_options(tmp_path, capsys):
    argv = [*SIM, "--out", str(tmp_path / "s"), "--payload", "5", "--stations", "2"]
    refuse(capsys, tmp_path, argv, "--stations", "--payload")


def test_simulate_torques_without_masses(tmp_path):
    """A correct result: a DH table without link masses gets seeded true masses, and the torques are finite."""
    assert cli_simulate(tmp_path / "s", "--poses", "20", "--test-poses", "5", "--torques", robot="arm7_dh") == 0
    _, header, rows = _table(tmp_path / "s" / "train.csv")
    assert {f"tau{k}" for k in range(1, 8)} <= set(header)
    assert any(abs(float(r[header.index("tau2")])) > 1.0 for r in rows)


# ------------------------------------------------------------------------------- convert --map payload: / torques:

MAP = "read: {delimiter: whitespace, header: false}\nunits: {length: mm, angle: deg}\njoints: {columns: 1-6}\n"
ROWS = "\n".join(
    " ".join(
        f"{v:.4f}"
        for v in [10.0 * k, -80 + k, 85 - k, 5.0, 90.0, 0.0, 812 - k, -191 + 9 * k, 425 + 7 * k, 5.0]
        + [1.0 + k, -30.0, -12.0, 2.0, 0.5, 0.1, 0.01, 0.02, 0.15]
    )  # fmt: skip
    for k in range(6)
)


def _convert_argv(tmp_path, map_text):
    (tmp_path / "in").mkdir(exist_ok=True)
    (tmp_path / "in" / "map.yaml").write_text(map_text)
    (tmp_path / "in" / "d.txt").write_text(ROWS + "\n")
    return ["convert", "--map", str(tmp_path / "in" / "map.yaml"), str(tmp_path / "in" / "d.txt"), "--out",
            str(tmp_path / "o.csv")]  # fmt: skip


def test_convert_payload_and_torques(tmp_path):
    """A correct result: payload with its centre of mass (mm in the MAP: m in the file) and six torques."""
    argv = _convert_argv(tmp_path, MAP + "position: {columns: 7-9}\npayload: [10, 17, 18, 19]\ntorques: 11-16\n")
    assert run_cli(argv) == 0
    _, header, rows = _table(tmp_path / "o.csv")
    assert header[-10:] == ["payload", "payload_x", "payload_y", "payload_z", *[f"tau{k}" for k in range(1, 7)]]
    assert float(rows[1][header.index("payload_z")]) == pytest.approx(0.15e-3)
    assert float(rows[1][header.index("tau1")]) == 2.0


@pytest.mark.parametrize(
    "extra, needles",
    [
        ("position: {columns: 7-9}\ntorques: 4-9\n", ["torques", "joints", "column 4"]),  # torques on joints and x,y,z
        ("position: {columns: 7-9}\npayload: 7\n", ["payload", "position", "column 7"]),  # payload on x: 812 "kg"
        ("position: {columns: 4-6}\n", ["position", "joints", "column 4"]),  # points on joint columns
        ("position: {columns: 7-9}\ntorques: 11-16\nextra: {tau: 1-6}\n", ["extra", "tau1"]),
        ("position: {columns: 7-9}\npayload: 10\nextra: {payload_x: 17}\n", ["extra", "payload_x"]),
        ("position: {columns: 7-9}\nextra: {payload_x: 17, payload_y: 18, payload_z: 19}\n", ["payload"]),
        ("position: {columns: 7-9}\npayload: [10, 17, 18]\n", ["payload", "one column (kg) or four"]),
        ("position: {columns: 7-9}\ntorques: 11-15\n", ["torques", "5 torque columns", "6 joints"]),
        ("position: {columns: 7-9}\npayload: 12\n", ["d.txt", "line 1", "column 'payload'", ">= 0"]),
    ],
    ids=[
        "torques-on-joints",
        "payload-on-x",
        "points-on-joints",
        "extra-tau-and-torques",
        "extra-com-and-payload",
        "com-without-payload",
        "payload-3-columns",
        "five-torques",
        "negative-payload",
    ],  # fmt: skip
)
def test_convert_load_map_refused(tmp_path, capsys, extra, needles):
    """Overlapping roles read one column as two quantities (a joint as a torque, x in mm as a payload in kg) and the
    second ``tau1..tau6`` of ``extra: {tau: ..}`` replaced ``torques:``'s without a word."""
    refuse(capsys, tmp_path, _convert_argv(tmp_path, MAP + extra), *needles)


# -------------------------------------------------------------------------------------- export and check-export


def test_export_cofitted_of_a_kinematic_run_is_its_chain(loaded, tmp_path, capsys):
    """A correct result: a run without effects has one chain; both --geometry choices write it and check-export
    finds it to rounding."""
    for g in ("standalone", "cofitted"):
        out = tmp_path / f"{g}.yaml"
        assert run_cli(["export", str(loaded / "r"), "--format", "dh", "--out", str(out), "--geometry", g]) == 0
        capsys.readouterr()
        assert main_out(["check-export", str(loaded / "r"), str(out)], capsys).startswith(str(out))
    assert (tmp_path / "standalone.yaml").read_text() == (tmp_path / "cofitted.yaml").read_text()


def main_out(argv, capsys) -> str:
    from torchcal.cli import main

    assert main(argv) == 0
    return capsys.readouterr().out


def test_check_export_of_a_missing_file(loaded, tmp_path, capsys):
    """It said "robot 'x.yaml' is neither a file nor a built-in robot; built-ins: ..." for a typo."""
    err = refuse(capsys, tmp_path, ["check-export", str(loaded / "r"), str(tmp_path / "x.yaml")], "x.yaml", "no such")
    assert "built-in" not in err, err


def test_check_export_of_a_directory(loaded, tmp_path, capsys):
    (tmp_path / "d.urdf").mkdir()
    refuse(capsys, tmp_path, ["check-export", str(loaded / "r"), str(tmp_path / "d.urdf")], "d.urdf", "directory")


def test_check_export_of_a_ur_ros2_file(loaded, tmp_path, capsys):
    """It said "expected a mapping with 'name', 'convention' and 'joints'" of torchcal's own ur-ros2 export."""
    assert run_cli(["export", str(loaded / "r"), "--format", "ur-ros2", "--out", str(tmp_path / "ur.yaml")]) == 0
    capsys.readouterr()
    refuse(capsys, tmp_path, ["check-export", str(loaded / "r"), str(tmp_path / "ur.yaml")], "ur.yaml", "ur-ros2")


def test_check_export_of_another_robot(loaded, tmp_path, capsys):
    """ur10's own description was 'checked' against a UR5 run: 391 mm apart, exit 0."""
    from torchcal.robot.load import resolve_robot_spec

    ur10 = str(resolve_robot_spec("ur10"))
    err = refuse(capsys, tmp_path, ["check-export", str(loaded / "r"), ur10], "ur10.yaml", "does not reproduce")
    assert " mm" in err


def test_check_export_with_an_upper_case_suffix(loaded, tmp_path, capsys):
    """check-export took 'E.URDF' and then said "unknown robot description type '.URDF'": it is refused at once, as
    --robot would refuse it, with the name that loads."""
    assert run_cli(["export", str(loaded / "r"), "--format", "urdf", "--out", str(tmp_path / "e.urdf")]) == 0
    (tmp_path / "e.urdf").rename(tmp_path / "E.URDF")
    capsys.readouterr()
    refuse(capsys, tmp_path, ["check-export", str(loaded / "r"), str(tmp_path / "E.URDF")], "E.URDF", "rename", ".urdf")


def test_check_export_of_an_empty_file(loaded, tmp_path, capsys):
    (tmp_path / "e.yaml").write_text("")
    refuse(capsys, tmp_path, ["check-export", str(loaded / "r"), str(tmp_path / "e.yaml")], "e.yaml")


def test_check_export_of_a_file_of_another_dof(loaded, tmp_path, capsys):
    from torchcal.robot.load import resolve_robot_spec

    panda = str(resolve_robot_spec("panda.urdf"))
    refuse(capsys, tmp_path, ["check-export", str(loaded / "r"), panda], "7 joints", "6")


def test_export_into_a_missing_run(tmp_path, capsys):
    refuse(capsys, tmp_path, ["export", str(tmp_path / "nope"), "--format", "dh", "--out", str(tmp_path / "e.yaml")],
           "nope")  # fmt: skip


def test_export_over_a_measurement_file(loaded, tmp_path, capsys):
    """A file torchcal did not write as an export (here: a campaign's CSV) is not replaced without --force."""
    (tmp_path / "data.yaml").write_text("q1,q2\n1,2\n")
    refuse(capsys, tmp_path, ["export", str(loaded / "r"), "--format", "dh", "--out", str(tmp_path / "data.yaml")],
           "data.yaml", "--force")  # fmt: skip
