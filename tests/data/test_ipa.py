"""The ipa-robot-accuracy importer: synthetic files in the IPA layout, then the real UR10 data set."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
import torch

import torchcal
from torchcal.data import convert_ipa, read_ipa, read_measurements
from torchcal.data.ipa import matrix_to_rotvec
from torchcal.errors import MeasurementFileError
from torchcal.estimate import fit_instrument_and_tool
from torchcal.robot import transforms as tf

# ----------------------------------------------------------------------------- synthetic files

JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
HEAD = [
    "Timestamp",
    "Goal x",
    "Goal y",
    "Goal z",
    "Goal roll",
    "Goal pitch",
    "Goal yaw",
    *JOINTS,
    "measurement_temperature",
]
HEADER_A = [
    *HEAD,
    "measurement_x",
    "measurement_y",
    "measurement_z",
    "measurement_rx",
    "measurement_ry",
    "measurement_rz",
]
HEADER_B = [
    *HEAD,
    "measurement_x",
    "measurement_std_x",
    "measurement_y",
    "measurement_std_y",
    "measurement_z",
    "measurement_std_z",
    "measurement_rx",
    "measurement_std_rx",
    "measurement_ry",
    "measurement_std_ry",
    "measurement_rz",
    "measurement_std_rz",
]
HANDEYE_D = [
    "flange_x",
    "flange_y",
    "flange_z",
    "flange_qx",
    "flange_qy",
    "flange_qz",
    "flange_qw",
    "measurement_temperature",
    "measurement_x",
    "measurement_std_x",
    "measurement_y",
    "measurement_std_y",
    "measurement_z",
    "measurement_std_z",
    "measurement_rx",
    "measurement_std_rx",
    "measurement_ry",
    "measurement_std_ry",
    "measurement_rz",
    "measurement_std_rz",
]

# Three poses in the Series B-D layout; the first and third share a goal (second visit, other IK branch).
ROWS_B = [
    "2,02011E+13;0,4;-0,4;0,8;2,96706;1,5708;1,5708;-0,908775;-0,052173;-1,92746;-1,16213;-2,05921;-0,000837151;"
    "21,86750031;-0,50720828;0,011904;-3343,1516;0,0080769;-426,95048;0,0088318;-90,14477;0,0014463;-30,089752;"
    "0,001215;-90,358505;0,0021268",
    "2,02011E+13;0,000121973;-0,365141;1,4273;1,56998;1,57013;-2,78E-05;-3,14159;-1,5708;0;-1,5708;0;0;"
    "21,9;383,76294;0,031674;-3240,8734;0,013252;201,93157;0,0037622;-90,179302;0,0011832;-20,118749;0,0013871;"
    "-90,169308;0,0041345",
    "2,02011E+13;0,4000000001;-0,4;0,8;2,96706;1,5708;1,5708;-0,908775;-1,88313;1,92746;-3,18587;-2,05921;"
    "-0,000741784;22;1,8451966;0,0068993;-3343,6855;0,016631;-425,73515;0,0097318;-90,213735;0,0024908;"
    "-30,006856;0,0023744;-90,255949;0,0030282",
]
ROWS_A = [
    "20200714235950;0,365141;-0,000212669;1,4273;1,57002;1,57007;1,57073;-1,5708;-1,5708;0,0;-1,5708;0,0;0,0;"
    "23,68;2361,9831;-1368,5474;119,39713;-90,409151;-59,885105;-90,887438",
    "20200714235959;0,8;0,6;0,9;1,7453299999999998;1,5708;1,5708;-2,14055;-2,08493;-0,837441;-0,218756;0,393594;"
    "-0,00187856;23,5;1685,2797;-1665,3456;-415,81103;-90,282663;-49,675357;-90,926009",
    "20200715000009;0,8;2,77556e-17;0,7;1,5708;1,7453299999999998;1,5708;-2,16052;-2,0273;-0,925227;-0,18811;"
    "0,588775;-0,176423;23,4;1686,8735;-1663,0997;-415,93957;-90,587143;-59,765542;-101,22108",
]


def write_ipa(
    tmp_path: Path,
    header,
    rows,
    *,
    name="measurements_test.csv",
    series="Series_X",
    bom=False,
    nul=False,
    newline="\r\n",
    tail="",
) -> Path:
    """Write an IPA-layout file (``;``, decimal commas, CRLF) under ``tmp_path/series``."""
    folder = tmp_path / series
    folder.mkdir(exist_ok=True)
    end = ("\x00 " if nul else "") + newline
    text = ";".join(header) + end + "".join(row + end for row in rows) + tail
    path = folder / name
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode("utf-8"))
    return path


def expect_error(path, *, line, column) -> MeasurementFileError:
    with pytest.raises(MeasurementFileError) as info:
        read_ipa(path)
    err = info.value
    assert path.name in str(err)
    assert (err.line, err.column) == (line, column), str(err)
    if line is not None:
        assert f"line {line}" in str(err)
    if column is not None:
        assert f"column '{column}'" in str(err)
    return err


def f64(values) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


def euler_xyz_deg(rx, ry, rz) -> torch.Tensor:
    """Intrinsic XYZ: R = Rx(rx) Ry(ry) Rz(rz), angles in degrees."""
    a = torch.stack([torch.as_tensor(v, dtype=torch.float64) for v in (rx, ry, rz)], dim=-1) * tf.DEG
    return tf.rot_x(a[..., 0]) @ tf.rot_y(a[..., 1]) @ tf.rot_z(a[..., 2])


def test_series_b_layout_units_and_columns(tmp_path):
    m = read_ipa(write_ipa(tmp_path, HEADER_B, ROWS_B))
    assert m.n == 3 and m.dof == 6 and m.q.dtype == torch.float64
    assert torch.equal(m.q[0], f64([-0.908775, -0.052173, -1.92746, -1.16213, -2.05921, -0.000837151]))
    assert torch.equal(m.q[1], f64([-3.14159, -1.5708, 0.0, -1.5708, 0.0, 0.0]))
    torch.testing.assert_close(m.p[0], f64([-0.50720828, -3343.1516, -426.95048]) / 1000, rtol=0, atol=1e-15)
    torch.testing.assert_close(m.sigma[1], f64([0.031674, 0.013252, 0.0037622]) / 1000, rtol=0, atol=1e-18)
    assert torch.equal(m.temperature, f64([21.86750031, 21.9, 22.0]))
    assert torch.equal(m.extra["row"], f64([0, 1, 2]))
    assert torch.equal(m.extra["goal_x"], f64([0.4, 0.000121973, 0.4000000001]))
    assert torch.equal(m.extra["goal_z"], f64([0.8, 1.4273, 0.8]))
    assert m.lines == (2, 3, 4)
    assert m.t is None and "destroyed" in m.meta["time"]
    assert m.meta["series"] == "X" and m.meta["robot"] == "ur10" and m.meta["licence"] == "MIT"
    assert m.meta["source"] == "ipa-robot-accuracy" and "CASE 2021" in m.meta["citation"]
    assert "sigma_replaced" not in m.meta
    # the T-Mac orientation: intrinsic XYZ degrees -> rotation vector [rad]
    rotvec = m.r
    expected = euler_xyz_deg(
        [-90.14477, -90.179302, -90.213735], [-30.089752, -20.118749, -30.006856], [-90.358505, -90.169308, -90.255949]
    )
    torch.testing.assert_close(tf.so3_exp(rotvec), expected, rtol=0, atol=1e-14)


def test_goal_ids_group_equal_goals_in_order_of_first_appearance(tmp_path):
    goals = [
        "0,4;-0,4;0,8;2,96706;1,5708;1,5708",
        "0,1;0,2;0,3;0;0;0",
        "0,4000000004;-0,4;0,8;2,96706;1,5708;1,5708",
        "0,1;0,2;0,3;0;0;0,000001",
        "0,1;0,2;0,3;0;0;-0",
        "0,4;-0,4;0,8;2,96706;1,5708;1,5708",
    ]
    rest = ";0,1;0,2;0,3;0,4;0,5;0,6;22;2000;-1000;100;-90;-60;-90"
    rows = [f"20200714163904;{g}{rest}" for g in goals]
    m = read_ipa(write_ipa(tmp_path, HEADER_A, rows))
    assert m.extra["goal_id"].tolist() == [0.0, 1.0, 0.0, 2.0, 1.0, 0.0]
    assert m.extra["row"].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]


def test_series_a_layout_intact_timestamps_give_t(tmp_path):
    m = read_ipa(write_ipa(tmp_path, HEADER_A, ROWS_A, series="Series_A"))
    assert m.meta["series"] == "A" and m.sigma is None
    assert torch.equal(m.t, f64([0.0, 9.0, 19.0]))  # across midnight
    assert "time" not in m.meta and "timestamp_s" not in m.extra
    assert m.extra["goal_y"][2].item() == 2.77556e-17
    torch.testing.assert_close(m.p[1], f64([1.6852797, -1.6653456, -0.41581103]), rtol=0, atol=1e-15)


def test_timestamps_out_of_order_leave_t_out(tmp_path):
    rows = [ROWS_A[0], ROWS_A[2], ROWS_A[1]]
    m = read_ipa(write_ipa(tmp_path, HEADER_A, rows))
    assert m.t is None
    assert "not non-decreasing" in m.meta["time"] and "line 4" in m.meta["time"]
    assert torch.equal(m.extra["timestamp_s"], f64([0.0, 19.0, 9.0]))


def test_zero_std_is_replaced_by_the_column_median(tmp_path):
    rows = list(ROWS_B)
    rows[1] = rows[1].replace(";0,031674;", ";0;").replace(";0,013252;", ";-0,0;")
    m = read_ipa(write_ipa(tmp_path, HEADER_B, rows))
    assert (m.sigma > 0).all()
    torch.testing.assert_close(
        m.sigma[1, :2], f64([(0.011904 + 0.0068993) / 2, (0.0080769 + 0.016631) / 2]) / 1000, rtol=1e-15, atol=0
    )
    assert m.meta["sigma_replaced"].startswith("2 ")


def test_bom_nul_bytes_trailing_spaces_lf_and_blank_lines(tmp_path):
    plain = read_ipa(write_ipa(tmp_path, HEADER_B, ROWS_B, name="plain.csv"))
    messy = read_ipa(
        write_ipa(
            tmp_path, HEADER_B, ROWS_B, name="messy.csv", bom=True, nul=True, newline="\n", tail="\r\n \r\n\x00\r\n"
        )
    )
    for name in ("q", "p", "sigma", "temperature"):
        assert torch.equal(getattr(plain, name), getattr(messy, name)), name
    assert messy.lines == (2, 3, 4)


@pytest.mark.parametrize(
    ("cell", "message"),
    [
        ("abc", "not a number"),
        ("", "empty cell"),
        ("nan", "not a number"),
        ("inf", "not a number"),
        ("1,2,3", "not a number"),
        ("1.234,5", "not a number"),
        ("1\x002", "not a number"),
        ("1_0", "not a number"),
    ],
)
def test_bad_cell_names_line_and_column(tmp_path, cell, message):
    cells = ROWS_B[2].split(";")
    cells[HEADER_B.index("elbow_joint")] = cell
    rows = [ROWS_B[0], ROWS_B[1], ";".join(cells)]
    err = expect_error(write_ipa(tmp_path, HEADER_B, rows, tail="\r\n"), line=4, column="elbow_joint")
    assert message in str(err)


def test_bad_cell_line_counts_blank_lines(tmp_path):
    rows = [ROWS_A[0], "", ROWS_A[1].replace(";23,5;", ";23,5x;")]
    expect_error(write_ipa(tmp_path, HEADER_A, rows), line=4, column="measurement_temperature")


def test_bad_timestamp_cell_is_an_error(tmp_path):
    rows = [ROWS_A[0], "2020-07-14" + ROWS_A[1][14:]]
    expect_error(write_ipa(tmp_path, HEADER_A, rows), line=3, column="Timestamp")


def test_short_row_names_the_first_missing_column(tmp_path):
    rows = [ROWS_B[0], ROWS_B[1].rsplit(";", 2)[0]]
    expect_error(write_ipa(tmp_path, HEADER_B, rows), line=3, column="measurement_rz")


def test_missing_and_duplicate_columns(tmp_path):
    header = [c for c in HEADER_A if c != "wrist_2_joint"]
    rows = [";".join(r.split(";")[:11] + r.split(";")[12:]) for r in ROWS_A]
    err = expect_error(write_ipa(tmp_path, header, rows, name="missing.csv"), line=1, column="wrist_2_joint")
    assert "missing" in str(err)
    header = [*HEADER_A[:-1], "measurement_x"]
    expect_error(write_ipa(tmp_path, header, ROWS_A, name="dup.csv"), line=1, column="measurement_x")


def test_handeye_files_are_rejected_clearly(tmp_path):
    row = (
        "4,73E-05;0,256;1,4273;-0,7071;6,37E-05;-2,09E-05;0,7071;20,74;2577,6154;0,00072644;-1073,9765;0,0016938;"
        "207,59394;0,0022376;-90,2738;0,0008138;-78,802752;0,0017754;-90,384222;0,0030775"
    )
    path = write_ipa(tmp_path, HANDEYE_D, [row], name="calibration_handeye.csv", nul=True, newline="\n")
    err = expect_error(path, line=1, column=None)
    assert "hand-eye" in str(err) and "no joint angles" in str(err)


def test_positions_in_metres_are_an_error_with_a_hint(tmp_path):
    rows = [
        r.replace("2361,9831;-1368,5474;119,39713", "2,3619831;-1,3685474;0,11939713")
        .replace("1685,2797;-1665,3456;-415,81103", "1,6852797;-1,6653456;-0,41581103")
        .replace("1686,8735;-1663,0997;-415,93957", "1,6868735;-1,6630997;-0,41593957")
        for r in ROWS_A
    ]
    err = expect_error(write_ipa(tmp_path, HEADER_A, rows), line=2, column="measurement_x")
    assert "millimetres" in err.hint


def test_empty_file_and_header_only(tmp_path):
    empty = tmp_path / "empty.csv"
    empty.write_bytes(b"\r\n\x00\r\n")
    expect_error(empty, line=None, column=None)
    expect_error(write_ipa(tmp_path, HEADER_A, []), line=1, column=None)


def test_convert_ipa_writes_the_contract_format(tmp_path):
    src = write_ipa(tmp_path, HEADER_B, ROWS_B)
    out = tmp_path / "out.csv"
    m = convert_ipa(src, out)
    back = read_measurements(out, dof=6, joint_limits=torchcal.load_robot("ur10").limits)
    assert m.r is not None and m.sigma_r is not None  # the T-Mac's orientation and its sigma are kept
    for name in ("q", "p", "sigma", "temperature", "r", "sigma_r"):
        assert torch.equal(getattr(back, name), getattr(m, name)), name
    assert back.t is None
    assert back.meta["series"] == "X" and back.meta["source"] == "ipa-robot-accuracy"
    assert set(back.extra) == set(m.extra)
    for key, value in m.extra.items():
        assert torch.equal(back.extra[key], value), key


def test_convert_ipa_writes_nothing_on_error(tmp_path):
    rows = [ROWS_B[0], ROWS_B[1].replace("383,76294", "383,76294 mm")]
    src = write_ipa(tmp_path, HEADER_B, rows)
    out = tmp_path / "out" / "converted.csv"
    out.parent.mkdir()
    with pytest.raises(MeasurementFileError) as info:
        convert_ipa(src, out)
    assert (info.value.line, info.value.column) == (3, "measurement_x")
    assert list(out.parent.iterdir()) == []


def test_matrix_to_rotvec_round_trips_at_every_angle():
    gen = torch.Generator().manual_seed(0)
    axes = torch.randn(64, 3, generator=gen, dtype=torch.float64)
    axes = axes / axes.norm(dim=1, keepdim=True)
    for angle in (0.0, 1e-12, 1e-6, 0.3, 2.0, math.pi - 1e-6, math.pi - 1e-10, math.pi):
        rotvec = axes * angle
        got = matrix_to_rotvec(tf.so3_exp(rotvec))
        if angle < math.pi - 1e-3:
            torch.testing.assert_close(got, rotvec, rtol=0, atol=1e-12)
        else:  # at pi the sign of the axis is a free choice
            torch.testing.assert_close(
                got.norm(dim=1), torch.full((64,), angle, dtype=torch.float64), rtol=0, atol=1e-7
            )
            assert (got * axes).sum(1).abs().sub(angle).abs().max() < 1e-7
            torch.testing.assert_close(tf.so3_exp(got), tf.so3_exp(rotvec), rtol=0, atol=1e-12)


def test_euler_conversion_matches_scipy():
    rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    gen = torch.Generator().manual_seed(1)
    euler = (torch.rand(200, 3, generator=gen, dtype=torch.float64) * 2 - 1) * f64([180.0, 90.0, 180.0])
    euler[:20, 1] = -90.0 + torch.rand(20, generator=gen, dtype=torch.float64) * 1e-3  # Series A: near gimbal lock
    ours = matrix_to_rotvec(euler_xyz_deg(euler[:, 0], euler[:, 1], euler[:, 2]))
    theirs = f64(rotation.from_euler("XYZ", euler.numpy(), degrees=True).as_rotvec())
    keep = theirs.norm(dim=1) < math.pi - 1e-6
    assert keep.sum() > 150
    torch.testing.assert_close(ours[keep], theirs[keep], rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- the real data set

SERIES = {  # folder, file, rows, distinct goals, temperature range [degC] (0.1 degC rounding)
    "A": ("Series_A", "measurements_grid.csv", 11911, 11911, (22.9, 23.7)),
    "B": ("Series_B", "measurements_joint_configurations.csv", 1495, 757, (21.6, 22.2)),
    "C": ("Series_C", "measurements_random_poses.csv", 2773, 2773, (21.7, 22.1)),
    "D": ("Series_D", "measurements_iso_cubes.csv", 632, 632, (20.7, 20.9)),
}
DEFAULT_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "ur10-ipa"


@pytest.fixture(scope="module")
def ipa_dir() -> Path:
    root = Path(os.environ.get("TORCHCAL_IPA_DATA", DEFAULT_DATA))
    if not (root / "Series_C").is_dir():
        pytest.skip(f"ur10-ipa data not found at {root}; set TORCHCAL_IPA_DATA")
    return root


@pytest.fixture(scope="module")
def real(ipa_dir):
    return {s: read_ipa(ipa_dir / folder / name) for s, (folder, name, *_) in SERIES.items()}


@pytest.fixture(scope="module")
def ur10():
    return torchcal.load_robot("ur10")


@pytest.mark.parametrize("series", list(SERIES))
def test_real_series_shapes_and_ranges(real, series):
    _, _, rows, goals, (t_lo, t_hi) = SERIES[series]
    m = real[series]
    assert m.n == rows and m.dof == 6
    assert m.meta["series"] == series
    assert int(m.extra["goal_id"].max()) + 1 == goals
    distance = m.p.norm(dim=1)
    # 1.5-3.5 m from the tracker; Series D actually reaches 3.71 m
    assert 1.5 < distance.min() and distance.max() < 3.8
    assert t_lo - 0.05 <= m.temperature.min() and m.temperature.max() <= t_hi + 0.05
    assert m.q.abs().max() <= 2 * math.pi
    assert m.t is None  # A: timestamps out of order at the end; B-D: destroyed by Excel
    if series == "A":
        assert m.sigma is None
        span = m.extra["timestamp_s"].max() - m.extra["timestamp_s"].min()
        assert 4 * 86400 < span < 5 * 86400  # 2020-07-14 to 07-18
    else:
        assert "destroyed" in m.meta["time"]
        assert 5e-6 < m.sigma.median() < 2e-5  # ~0.01 mm


def test_real_series_b_visits_most_goals_twice(real):
    counts = torch.bincount(real["B"].extra["goal_id"].long())
    assert (counts == 2).sum() == 738 and (counts == 1).sum() == 19


@pytest.mark.parametrize("series", list(SERIES))
def test_real_goals_match_nominal_fk(real, ur10, series):
    """Rz(pi) FK(q) Trans(0, 0, 109 mm) is the commanded T-Mac TCP: joint order, units and frames are right."""
    m = real[series].subset(slice(None, None, 10))
    with torch.no_grad():
        tcp = tf.transform_points(ur10(m.q), f64([0.0, 0.0, 0.109]))
    goal = torch.stack([m.extra["goal_x"], m.extra["goal_y"], m.extra["goal_z"]], dim=1)
    error = (tcp * f64([-1.0, -1.0, 1.0]) - goal).norm(dim=1)
    assert error.median() < 0.15e-3 and error.max() < 1e-3


def test_real_nominal_fit_series_c(real, ur10):
    """Nominal UR10 + fitted tracker pose and lever arm: the uncalibrated ~1 mm error of docs/real-data.md."""
    m = real["C"]
    with torch.no_grad():
        T_tracker_base, lever, rms = fit_instrument_and_tool(ur10(m.q), m.p)
    assert 0.7e-3 < rms < 1.2e-3
    assert abs(lever[2].item() - 0.093) < 0.003 and lever[:2].norm() < 0.002  # T-Mac ~93 mm along flange z
    torch.testing.assert_close(T_tracker_base[:3, :3] @ T_tracker_base[:3, :3].T, torch.eye(3, dtype=torch.float64))


def test_real_orientation_matches_scipy(real, ipa_dir):
    rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    m = real["D"]
    lines = (ipa_dir / "Series_D" / "measurements_iso_cubes.csv").read_text().splitlines()
    header = lines[0].split(";")
    cols = [header.index(c) for c in ("measurement_rx", "measurement_ry", "measurement_rz")]
    euler = [[float(line.split(";")[k].replace(",", ".")) for k in cols] for line in lines[1:] if line]
    theirs = f64(rotation.from_euler("XYZ", euler, degrees=True).as_rotvec())
    ours = m.r
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-12)


def test_real_convert_round_trips(real, ipa_dir, ur10, tmp_path):
    out = tmp_path / "series_d.csv"
    m = convert_ipa(ipa_dir / "Series_D" / "measurements_iso_cubes.csv", out)
    back = read_measurements(out, dof=6, joint_limits=ur10.limits, robot_name="ur10")
    assert back.n == 632
    for name in ("q", "p", "sigma", "temperature"):
        assert torch.equal(getattr(back, name), getattr(m, name)), name
    assert back.meta["series"] == "D" and back.meta["citation"] == "Landgraf et al., IEEE CASE 2021"


@pytest.mark.parametrize("series", ["B", "D"])
def test_real_handeye_files_are_rejected(ipa_dir, series):
    with pytest.raises(MeasurementFileError, match="hand-eye") as info:
        read_ipa(ipa_dir / f"Series_{series}" / "calibration_handeye.csv")
    assert info.value.line == 1
