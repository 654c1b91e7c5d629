"""Hostile inputs, round 3 (issue 34 items 7-9, issue 35): vendor robot files, noise-level warnings and ``--quiet``,
orientation rows in the gross-error screening, and the internal errors and silent wrong results of issue 35 (items
1, 4-7, 10, 11; 2, 3 and 8 are ``plan``'s, 9 and the ``station`` parts of 11 ``station``'s).

Every case is a clear refusal (exit 2, naming the file, row, column or parameter, nothing written) or a correct
result; never exit 1, never a hang. Campaigns are tiny and module-scoped.
"""

import errno
import json
import math
import os
from pathlib import Path

import pytest
import test_hostile as hostile
import torch
from _cli import calibrate, cli_simulate, deadline, refused, snapshot

import torchcal
import torchcal._outdir
from torchcal.cli import main
from torchcal.use.rundir import load_model

write = hostile.write


# ------------------------------------------------------- issue 34 item 7: a mimic whose source is off the chain

VENDOR_COLUMN = """<?xml version="1.0"?>
<robot name="vendor_column">
  <link name="base"/><link name="virtual"/><link name="seg1"/><link name="seg2"/><link name="arm"/><link name="flange"/>
  <joint name="column_prismatic_joint" type="prismatic">
    <parent link="base"/><child link="virtual"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.6" effort="0" velocity="0"/>
  </joint>
  <joint name="column_lower_joint" type="prismatic">
    <parent link="base"/><child link="seg1"/><origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.3" effort="0" velocity="0"/>
    <mimic joint="column_prismatic_joint" multiplier="0.5" offset="0"/>
  </joint>
  <joint name="column_middle_joint" type="prismatic">
    <parent link="seg1"/><child link="seg2"/><origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.3" effort="0" velocity="0"/>
    <mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.01"/>
  </joint>
  <joint name="pan" type="revolute">
    <parent link="seg2"/><child link="arm"/><origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="0" velocity="0"/>
  </joint>
  <joint name="tilt" type="revolute">
    <parent link="arm"/><child link="flange"/><origin xyz="0.5 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="0" velocity="0"/>
  </joint>
</robot>
"""


def test_a_mimic_source_on_a_side_branch_becomes_a_reading(tmp_path):
    robot = torchcal.load_robot(write(tmp_path / "column.urdf", VENDOR_COLUMN))
    assert robot.joint_names == ["column_lower_joint", "column_middle_joint", "pan", "tilt"]
    assert robot.reading_names == ["column_prismatic_joint", "pan", "tilt"] and robot.dof == 3
    A = robot.readings.matrix().detach()
    assert A[:, 0].tolist() == [0.5, 0.5, 0.0, 0.0] and robot.readings.offset.tolist() == [0.0, 0.01, 0.0, 0.0]
    # the column's reading takes the range its segments allow: 0.3 m each at half the reading
    assert robot.limits[0].tolist() == pytest.approx([0.0, 0.6])
    with deadline(120):
        assert (
            cli_simulate(tmp_path / "s", "--poses", "20", "--test-poses", "5", robot=str(tmp_path / "column.urdf")) == 0
        )


def test_a_mimic_of_nothing_is_still_refused(tmp_path):
    text = VENDOR_COLUMN.replace(
        'mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.01"', 'mimic joint="lift"'
    )
    with pytest.raises(torchcal.RobotSpecError, match="mimics joint 'lift', which is not a movable joint"):
        torchcal.load_robot(write(tmp_path / "column.urdf", text))


# ---------------------------------- issue 35 items 5 and 11: fewer readings than joints; a run's URDF as --robot

FANUC = Path(__file__).resolve().parents[1] / "robot" / "data" / "fanuc_like.yaml"
#: the FANUC-like parallelogram arm whose wrist's last joint turns with the one before (a cable differential): six
#: model joints, five readings
FEWER = "[[1,0,0,0,0], [0,1,0,0,0], [0,-1,-1,0,0], [0,0,0,-1,0], [0,0,0,0,-1], [0,0,0,0,-1]]"


@pytest.fixture(scope="module")
def fewer(tmp_path_factory):
    root = tmp_path_factory.mktemp("fewer")
    text = FANUC.read_text().split("readings:")[0] + f"readings:\n  coupling: {FEWER}\n"
    robot = write(root / "fewer.yaml", text)
    assert cli_simulate(root / "s", "--poses", "40", "--test-poses", "5", "--seed", "2", robot=str(robot)) == 0
    # the file's '# robot:' line names fewer.yaml; the run's URDF is the same robot under another file name
    data = write(
        root / "train.csv", "".join(x for x in (root / "s" / "train.csv").open() if not x.startswith("# robot"))
    )
    return robot, data


def _calibrate(data, robot, out) -> int:
    return main(["calibrate", str(data), "--robot", str(robot), "--method", "kinematic", "--out", str(out), "--quiet"])


@pytest.fixture(scope="module")
def fewer_run(fewer, tmp_path_factory):
    """The kinematic run of :func:`fewer` and its exit status (before the fix: 1, an IndexError writing the URDF)."""
    robot, data = fewer
    out = tmp_path_factory.mktemp("fewer_run") / "c"
    with deadline(300):
        return _calibrate(data, robot, out), out


def test_fewer_readings_than_joints_write_their_urdf(fewer_run):
    code, run = fewer_run
    assert code == 0
    urdf = torchcal.load_robot(run / "robot_calibrated.urdf")
    assert (urdf.dof, urdf.n_joints) == (5, 6) and urdf.reading_names == ["J1", "J2", "J3", "J4", "J5"]


def test_the_run_urdf_of_a_parallelogram_arm_works_as_robot(fewer, fewer_run, tmp_path):
    robot, data = fewer
    code, first = fewer_run
    assert code == 0
    with deadline(300):
        assert _calibrate(data, first / "robot_calibrated.urdf", tmp_path / "again") == 0
    one, two = (json.loads((d / "report.json").read_text()) for d in (first, tmp_path / "again"))
    # the run's URDF is its calibrated robot (readings map included): calibrated again from it, it starts where the
    # first run ended (before the fix: refused, its readings taken for the model's joints)
    assert two["rmse_before_mm"] == pytest.approx(one["rmse_after_mm"], rel=1e-3)
    assert two["rmse_after_mm"] == pytest.approx(one["rmse_after_mm"], rel=0.05)


def test_an_old_run_urdf_without_its_readings_map_is_refused(fewer_run, tmp_path, capsys):
    _, run = fewer_run
    text = (run / "robot_calibrated.urdf").read_text()
    old = write(tmp_path / "old.urdf", "\n".join(x for x in text.splitlines() if "readings map (JSON)" not in x))
    with pytest.raises(torchcal.RobotSpecError, match="older torchcal"):
        torchcal.load_robot(old)


def test_readings_ratios_print_without_a_unit(fewer_run):
    """Issue 34 item 7: report.md printed a ratio as a length (``readings.c2_2 | -4.2899 mm`` for -0.00429)."""
    code, run = fewer_run
    assert code == 0
    lines = [x for x in (run / "report.md").read_text().splitlines() if x.startswith("| readings.c")]
    assert lines and not any("mm" in x or "″" in x for x in lines), lines
    rep = json.loads((run / "report.json").read_text())
    entry = next(e for e in rep["parameters"]["estimated"] if e["name"] == "readings.c3_2")
    assert f"| readings.c3_2 | {entry['correction']:.6g} |" in "\n".join(lines)


# ---------------------------------------------- issue 35 item 1: a readings ratio that absorbs a unit error


def _scaled_column(src: Path, dst: Path, column: int, factor: float) -> Path:
    """``src`` without its ``# robot:`` line, data column ``column`` (0-based) times ``factor``."""
    out, header = [], None
    for line in src.read_text().splitlines():
        if line.startswith("#"):
            out += [] if line.startswith("# robot") else [line]
        elif header is None:
            header = line
            out.append(line)
        else:
            cells = line.split(",")
            cells[column] = repr(float(cells[column]) * factor)
            out.append(",".join(cells))
    return write(dst, "\n".join(out) + "\n")


def test_a_ratio_that_absorbs_a_unit_error_stops_the_run(tmp_path, capsys):
    """The track of ``ur10_track`` read in units 10 % off (an identity ``readings:`` block makes its ratio free): the
    ratio moved by 0.11, 111 x its 0.1 % prior, and the run went on (exit 0); now it stops as a geometric correction
    beyond its prior does."""
    track = Path(torchcal.robot.load.resolve_robot_spec("ur10_track"))
    robot = write(
        tmp_path / "track.yaml",
        track.read_text()
        + "readings:\n  coupling: "
        + str([[1.0 if i == k else 0.0 for k in range(7)] for i in range(7)])
        + "\n",
    )
    assert cli_simulate(tmp_path / "s", "--poses", "50", "--test-poses", "5", "--seed", "3", robot="ur10_track") == 0
    data = _scaled_column(tmp_path / "s" / "train.csv", tmp_path / "train.csv", 0, 0.9)
    with deadline(300):
        assert _calibrate(data, robot, tmp_path / "c") == 2
    refused(capsys, "train.csv", "readings.c1_1", "x its prior", "another unit")
    assert not (tmp_path / "c").exists()


def test_a_singular_fit_of_a_readings_map_hints_at_the_signs(fewer, tmp_path, monkeypatch, capsys):
    """Issue 34 item 7: a ``readings:`` block with only ``q3 = -(J2+J3)`` for an arm whose wrist readings are also
    reversed failed with a bare "normal matrix singular". The solver's ending is forced here (the real data are the
    vendor's); the message must say what to try."""
    from torchcal.estimate import fit as fit_module
    from torchcal.estimate.lm import FitStatus

    real = fit_module.levenberg_marquardt

    def singular(*args, **kwargs):
        res = real(*args, **kwargs)
        res.status, res.message = FitStatus.FAILED_SOLVE, "the normal matrix was singular (rank deficient)"
        return res

    monkeypatch.setattr(fit_module, "levenberg_marquardt", singular)
    robot, data = fewer
    with deadline(300):
        assert _calibrate(data, robot, tmp_path / "c") == 2
    refused(capsys, "normal matrix was singular", "try the sign of each reading")
    assert not (tmp_path / "c").exists()


# ------------------------------------------------------- issue 35 items 6, 11: station labels that cannot be used


def _labelled(src: Path, dst: Path, label) -> Path:
    """``src`` with a ``station`` column, row ``i`` (0-based) labelled ``label(i)``."""
    out, header, i = [], None, 0
    for line in src.read_text().splitlines():
        if line.startswith("#"):
            out.append(line)
        elif header is None:
            header = line
            out.append(line + ",station")
        else:
            out.append(f"{line},{label(i)}")
            i += 1
    return write(dst, "\n".join(out) + "\n")


@pytest.mark.parametrize(
    "label, needles",
    [
        # every row its own station: IndexError (min() of an empty training set) before the fix
        (lambda i: f"S{i}", ["line 6, column 'station'", "station 'S0' was measured at 1 pose", "a label per row"]),
        # "1" and "1.0": two stations before the fix, though the numbers are equal
        (
            lambda i: "1" if i % 2 else "1.0",
            ["line 7, column 'station'", "label '1' is the number of an earlier label '1.0'"],
        ),
    ],
)
def test_station_labels_that_cannot_be_stations_are_refused(campaign, tmp_path, capsys, label, needles):
    data = _labelled(campaign / "train.csv", tmp_path / "st.csv", label)
    before = snapshot(tmp_path)
    with deadline(120):
        assert calibrate(data, tmp_path / "c") == 2
    refused(capsys, "st.csv", *needles)
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------- issue 35 item 7: a full disk, names too long


def _full_disk(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize("command", ["calibrate", "simulate"])
def test_a_full_disk_is_a_refusal_that_writes_nothing(campaign, tmp_path, monkeypatch, capsys, command):
    """Every run directory is written into a temporary that is renamed last (``torchcal._outdir``): the disk fills
    up before the rename. ``calibrate`` exited 1 ("this is a bug")."""
    monkeypatch.setattr(torchcal._outdir, "_write_listings", _full_disk)
    before = snapshot(tmp_path)
    with deadline(300):
        if command == "calibrate":
            code = calibrate(campaign / "train.csv", tmp_path / "out")
        else:
            code = cli_simulate(tmp_path / "out", "--poses", "20", "--test-poses", "5")
    assert code == 2
    refused(capsys, "No space left on device", "nothing was written")
    assert snapshot(tmp_path) == before


def test_a_full_disk_in_compensate_writes_nothing(run_dir, campaign, tmp_path, monkeypatch, capsys):
    targets = write(
        tmp_path / "targets.csv",
        "x,y,z\n"
        + "".join(",".join(c.split(",")[6:9]) + "\n" for c in (campaign / "test.csv").read_text().splitlines()[5:8]),
    )
    monkeypatch.setattr(os, "replace", _full_disk)
    before = snapshot(tmp_path)
    with deadline(300):
        assert main(["compensate", str(run_dir), str(targets), "--out", str(tmp_path / "q.csv"), "--quiet"]) == 2
    refused(capsys, "No space left on device")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("command", ["predict", "calibrate"])
@pytest.mark.parametrize("long", ["name", "path"])
def test_an_out_name_beyond_the_file_system_is_refused(run_dir, campaign, tmp_path, capsys, command, long):
    """An ``--out`` name over 255 bytes, or a path over PATH_MAX (4096): OSError, exit 1, before the fix."""
    out = tmp_path / ("n" * 300) if long == "name" else tmp_path.joinpath(*["d" * 200] * 22) / "out"
    before = snapshot(tmp_path)
    with deadline(300):
        if command == "predict":
            code = main(["predict", str(run_dir), str(campaign / "test.csv"), "--out", str(out / "p.csv"), "--quiet"])
        else:
            code = calibrate(campaign / "train.csv", out)
    assert code == 2
    refused(capsys, "error")
    assert snapshot(tmp_path) == before


# ---------------------------------------------- issue 34 item 8: noise-level warnings, held joints, --quiet


def _beyond(campaign: Path, dst: Path, delta: float) -> Path:
    """The training row of the largest q2, moved ``delta`` beyond it."""
    comments, header, rows = [], None, []
    for line in (campaign / "train.csv").read_text().splitlines():
        if line.startswith("#"):
            comments.append(line)
        elif header is None:
            header = line.split(",")
        else:
            rows.append(line.split(","))
    k = header.index("q2")
    top = max(rows, key=lambda r: float(r[k]))
    top = [*top[:k], repr(float(top[k]) + delta), *top[k + 1 :]]
    return write(dst, "\n".join(comments + [",".join(header), ",".join(top)]) + "\n")


@pytest.mark.parametrize("delta, quiet, warned", [(2.5e-7, False, False), (0.3, False, True), (0.3, True, False)])
def test_predict_warns_beyond_the_noise_and_not_under_quiet(run_dir, campaign, tmp_path, capsys, delta, quiet, warned):
    """A pose 2.5e-7 rad beyond the region is a training pose within the readings' noise: no warning (before: one,
    on every such row); ``--quiet`` silences the warnings (before: printed)."""
    data = _beyond(campaign, tmp_path / "rows.csv", delta)
    quiet_flag = ["--quiet"] if quiet else []
    assert main(["predict", str(run_dir), str(data), "--out", str(tmp_path / "p.csv"), *quiet_flag]) == 0
    err = capsys.readouterr().err
    assert ("beyond the calibrated region" in err) is warned, err
    if quiet:
        assert err == ""


def test_a_joint_held_still_is_held_not_outside():
    """A campaign that moves two joints only: the held joint's readings scatter by 1e-4 rad about 0, and every row
    was named as outside the calibrated region; a held joint moved away is named as held."""
    from types import SimpleNamespace

    from torchcal.cli import outside_rows

    region = torch.tensor([[-1.0, -1.0, -5e-5], [1.0, 1.0, 5e-5]], dtype=torch.float64)
    model = SimpleNamespace(region=region, robot=SimpleNamespace(joint_types=("revolute",) * 3))
    q = torch.tensor([[0.5, 0.5, 1e-4], [0.5, 0.5, -1e-4], [0.5, 0.5, 0.4], [1.3, 0.0, 0.0]], dtype=torch.float64)
    rows = outside_rows(model, q)
    assert [i for i, _ in rows] == [2, 3]
    assert "q3 moved 0.4 rad from where the calibration held it" in rows[0][1]
    assert "0.3 rad beyond the calibrated region (q1)" in rows[1][1]


# ------------------------------------------------ issue 34 item 9: orientation rows in the gross-error screening


def _turned_row(src: Path, dst: Path, row: int, deg: float) -> tuple[Path, int]:
    """``src`` with data row ``row`` (0-based)'s orientation turned ``deg`` about its x axis; and its file line."""
    from torchcal.robot.transforms import so3_exp, so3_log

    lines = src.read_text().splitlines()
    head = next(i for i, x in enumerate(lines) if not x.startswith("#"))
    cols, k = lines[head].split(","), head + 1 + row
    cells = lines[k].split(",")
    at = [cols.index(n) for n in ("rx", "ry", "rz")]
    r = torch.tensor([float(cells[j]) for j in at], dtype=torch.float64)
    turn = torch.tensor([math.radians(deg), 0.0, 0.0], dtype=torch.float64)
    for j, v in zip(at, so3_log(so3_exp(r) @ so3_exp(turn)).tolist()):
        cells[j] = repr(v)
    lines[k] = ",".join(cells)
    return write(dst, "\n".join(lines) + "\n"), k + 1


@pytest.fixture(scope="module")
def oriented(tmp_path_factory):
    root = tmp_path_factory.mktemp("oriented")
    assert cli_simulate(root / "s", "--poses", "60", "--test-poses", "5", "--seed", "5", "--orientation", "0.01") == 0
    return root / "s"


@pytest.mark.parametrize("deg", [0.0, 11.7])
def test_an_orientation_gross_error_is_screened_out(oriented, tmp_path, deg):
    """A row whose orientation is 11.7 deg off: kept with "0 outliers" before stop 39, rejected whole after it, now
    its orientation alone is left out and its (sound) position fitted."""
    data, line = _turned_row(oriented / "train.csv", tmp_path / "train.csv", 9, deg)
    with deadline(300):
        assert calibrate(data, tmp_path / "c") == 0
    report = json.loads((tmp_path / "c" / "report.json").read_text())
    outliers = report["outliers"]
    dropped = [r for part in ("training", "holdout") for r in outliers[part]["orientation_dropped"]]
    assert [r for part in ("training", "holdout") for r in outliers[part]["rows"]] == []  # no row lost
    n_rows = report["n_train"] + report["n_holdout"]
    assert n_rows == 60
    if deg == 0.0:  # clean rows: nothing left out
        assert dropped == []
    else:
        assert [r["line"] for r in dropped] == [line] and "11.7 deg off" in dropped[0]["hint"]
        assert "position is used" in dropped[0]["hint"]
        part = next(p for p in ("training", "holdout") if outliers[p]["orientation_dropped"])
        if part == "training":
            assert report["orientation"]["rows_fitted"] == report["n_train"] - 1


# ------------------------------------------------ issue 35 item 4: orientations that are no rotation of the probe


def test_random_orientations_are_refused(oriented, tmp_path, capsys):
    """Random rx, ry, rz calibrated with exit 0 and nothing on stderr (held-out orientation error 129 deg)."""
    g = torch.Generator().manual_seed(0)
    lines = (oriented / "train.csv").read_text().splitlines()
    head = next(i for i, x in enumerate(lines) if not x.startswith("#"))
    at = [lines[head].split(",").index(n) for n in ("rx", "ry", "rz")]
    for k in range(head + 1, len(lines)):
        cells = lines[k].split(",")
        v = torch.randn(3, generator=g, dtype=torch.float64)
        v = v / v.norm() * float(torch.rand(1, generator=g, dtype=torch.float64)) * math.pi
        for j, x in zip(at, v.tolist()):
            cells[j] = repr(x)
        lines[k] = ",".join(cells)
    data = write(tmp_path / "random.csv", "\n".join(lines) + "\n")
    with deadline(300):
        assert calibrate(data, tmp_path / "c") == 2
    refused(capsys, "random.csv, column 'rx'", "do not turn with the robot")
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize(
    "statistic, reading, said",
    [
        (2607.0, "mistake", "warning: the global test failed by far: variance factor 2607"),
        (2607.0, "model", "note: the global test fails (variance factor 2607"),
        (1.5, "model", None),
        (0.9, "agrees", None),
    ],
)
def test_a_global_test_failed_by_far_says_what_it_found(capsys, monkeypatch, statistic, reading, said):
    """A real campaign fails the global test by far and is told what the model leaves against the instrument's noise
    (a note, no unit hint); the unit and description hint is a warning only where the test reads as a mistake."""
    from torchcal import _console
    from torchcal.cli import _warn_global_test

    monkeypatch.setattr(_console, "_quiet", False)  # an earlier command of this process may have left --quiet on
    gt = {
        "statistic": statistic,
        "threshold": 1.06,
        "passed": statistic <= 1.06,
        "alpha": 0.05,
        "redundancy": 1000,
        "noise": {"sigma_m": 1e-5, "unit": "m", "source": "stated", "dof": 0},
        "unexplained_mm": 0.14,
        "times_noise": 8.1,
        "reach_m": 1.3,
        "geometric_share_of_reach": 0.02 if reading == "mistake" else 3.8e-4,
        "reading": reading,
    }
    _warn_global_test(gt)
    err = capsys.readouterr().err
    if said is None:
        assert err == ""
    else:
        assert said in err, err
        assert ("joint column in degrees" in err) is (reading == "mistake"), err
        assert "leaves 0.14" in err, err
        assert "8.1 times the noise level (10 um per axis, as the file's sx, sy, sz state it)" in err, err


# ------------------------------------------------------------- issue 35 item 10: name the cause


def test_a_readings_ratio_of_1e12_is_refused_at_load(tmp_path):
    """Passed ``simulate`` and failed ``calibrate`` with 'observation covariance of pose 0 is not positive definite'."""
    text = FANUC.read_text().replace("[0,-1,-1,0,0,0]", "[0,-1e12,-1,0,0,0]")
    with pytest.raises(torchcal.RobotSpecError, match=r"readings.coupling' has a ratio of size 1e\+12"):
        torchcal.load_robot(write(tmp_path / "r.yaml", text))


def test_a_mimic_multiplier_of_1e12_is_refused_at_load(tmp_path):
    text = VENDOR_COLUMN.replace('multiplier="0.5" offset="0.01"', 'multiplier="1e12" offset="0.01"')
    with pytest.raises(torchcal.RobotSpecError, match="joint 'column_middle_joint': mimic multiplier 1e\\+12"):
        torchcal.load_robot(write(tmp_path / "column.urdf", text))


def test_a_prior_scaled_by_1e20_is_refused_naming_the_covariance(run_dir, campaign, tmp_path, capsys):
    """Gave 'normal matrix singular'."""
    import shutil

    prior = tmp_path / "prior"
    shutil.copytree(run_dir, prior)
    state = torch.load(prior / "covariance.pt", weights_only=True)
    state["covariance"] = state["covariance"] * 1e20
    torch.save(state, prior / "covariance.pt")
    lines = (campaign / "test.csv").read_text().splitlines()
    head = next(i for i, x in enumerate(lines) if not x.startswith("#"))
    rows = write(tmp_path / "rows.csv", "\n".join(lines[: head + 11]) + "\n")
    before = snapshot(tmp_path)
    with deadline(300):
        assert calibrate(rows, tmp_path / "c", "--prior", str(prior)) == 2
    refused(capsys, "covariance.pt gives", "damaged or was scaled")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("quiet", [False, True])
def test_compensate_does_not_warn_about_its_own_solutions(run_dir, tmp_path, capsys, quiet):
    """Targets the run's model reaches at the region's edge plus 5e-5 rad and plus 0.3 rad in q2: the first was named
    as outside the calibrated region (issue 34 item 8: compensate warned about its own solutions at 2-6e-5 rad); the
    second still is, and ``--quiet`` prints nothing at all (before: the warnings)."""
    model = load_model(run_dir)[0]
    lo, hi = model.region
    q = ((lo + hi) / 2).repeat(2, 1)
    q[0, 1], q[1, 1] = hi[1] + 5e-5, hi[1] + 0.3
    p = model.predict(q)
    rows = [",".join(repr(float(v)) for v in [*q[i].tolist(), *p[i].tolist()]) for i in range(2)]
    targets = write(tmp_path / "targets.csv", "q1,q2,q3,q4,q5,q6,x,y,z\n" + "\n".join(rows) + "\n")
    flags = ["--quiet"] if quiet else []
    with deadline(300):
        assert main(["compensate", str(run_dir), str(targets), "--out", str(tmp_path / "q.csv"), *flags]) == 0
    err = capsys.readouterr().err
    if quiet:
        assert err == ""
    else:
        # the middle of every joint's range may turn the tool beyond the cone of the calibration's tool axes: that
        # flag is right; the region's flag at the edge is not
        line2 = [line for line in err.splitlines() if "line 2:" in line]
        assert not any("beyond the calibrated region" in line for line in line2), err
        assert "line 3: the pose lies 0.3 rad beyond the calibrated region (q2)" in err, err
