"""Measurement files: reading, validation, units and exact round trips (contract section 1)."""

from __future__ import annotations

import math
import os

import pytest
import torch

import torchcal.data.measurements as measurements_module
from torchcal.data import Measurements, read_measurements, write_measurements
from torchcal.errors import MeasurementFileError, OptionError, ShapeError

HEADER = "q1,q2,q3,x,y,z"
GOOD_ROWS = [
    "0.1,-0.2,0.3,1.5,0.25,0.75",
    "0.4,0.5,-0.6,1.25,-0.5,0.5",
    "-0.7,0.8,0.9,2.0,0.125,1.0",
]


def write(tmp_path, lines, name="meas.csv", newline="\n", bom=False):
    path = tmp_path / name
    text = newline.join(lines) + newline
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode("utf-8"))
    return path


def expect_error(path, *, line, column, **kwargs) -> MeasurementFileError:
    """Read ``path``, expect a MeasurementFileError at ``line``/``column``, return it."""
    with pytest.raises(MeasurementFileError) as info:
        read_measurements(path, **kwargs)
    err = info.value
    text = str(err)
    assert path.name in text
    assert err.line == line, text
    assert err.column == column, text
    if line is not None:
        assert f"line {line}" in text
    if column is not None:
        assert f"column '{column}'" in text
    return err


# --------------------------------------------------------------------------- good files


def test_reads_good_file_with_comments_meta_and_blank_lines(tmp_path):
    path = write(
        tmp_path,
        [
            "# robot: ur5",
            "# measured with a Leica AT960, free text: with a colon",
            "#tracker_serial:  AT960-123  ",
            "",
            HEADER + ",t,temperature,pose_id",
            GOOD_ROWS[0] + ",0.0,21.5,7",
            "",
            GOOD_ROWS[1] + ",1.0,21.6,3",
            "   ",
            GOOD_ROWS[2] + ",1.0,21.7,5",
            "",
        ],
    )
    m = read_measurements(path, dof=3)
    assert m.n == 3 and m.dof == 3
    assert m.source == str(path)
    assert m.meta == {"robot": "ur5", "tracker_serial": "AT960-123"}
    assert m.lines == (6, 8, 10)
    torch.testing.assert_close(m.q[1], torch.tensor([0.4, 0.5, -0.6], dtype=torch.float64), rtol=0, atol=0)
    torch.testing.assert_close(m.p[2], torch.tensor([2.0, 0.125, 1.0], dtype=torch.float64), rtol=0, atol=0)
    assert m.t.tolist() == [0.0, 1.0, 1.0]  # equal timestamps are allowed (non-decreasing)
    assert m.temperature.tolist() == [21.5, 21.6, 21.7]
    assert m.sigma is None
    assert list(m.extra) == ["pose_id"]
    assert m.extra["pose_id"].tolist() == [7.0, 3.0, 5.0]
    for x in (m.q, m.p, m.t, m.temperature, m.extra["pose_id"]):
        assert x.dtype == torch.float64


def test_column_order_is_free_and_extras_keep_file_order(tmp_path):
    path = write(
        tmp_path,
        [
            "b_extra,z,q2,x,a_extra,q1,y",
            "1,3.0,0.2,1.0,2,0.1,2.0",
        ],
    )
    m = read_measurements(path)
    assert m.q.tolist() == [[0.1, 0.2]]
    assert m.p.tolist() == [[1.0, 2.0, 3.0]]
    assert list(m.extra) == ["b_extra", "a_extra"]


def test_bom_and_crlf_are_tolerated(tmp_path):
    plain = read_measurements(write(tmp_path, ["# k: v", HEADER, *GOOD_ROWS], name="plain.csv"))
    dos = read_measurements(write(tmp_path, ["# k: v", HEADER, *GOOD_ROWS], name="dos.csv", newline="\r\n", bom=True))
    assert dos.meta == {"k": "v"}
    assert dos.lines == plain.lines == (3, 4, 5)
    assert torch.equal(dos.q, plain.q) and torch.equal(dos.p, plain.p)


def test_bom_with_crlf_error_names_the_right_line(tmp_path):
    path = write(tmp_path, ["# c", HEADER, GOOD_ROWS[0], "0.1,0.2,0.3,1.0,abc,1.0"], newline="\r\n", bom=True)
    expect_error(path, line=4, column="y")


def test_positions_optional_when_not_required(tmp_path):
    path = write(tmp_path, ["q1,q2,t", "0.1,0.2,0.0", "0.3,0.4,1.0"])
    m = read_measurements(path, require_positions=False)
    assert m.p is None and m.dof == 2


def test_sigma_columns(tmp_path):
    path = write(tmp_path, [HEADER + ",sx,sy,sz", GOOD_ROWS[0] + ",1e-5,2e-5,3e-5"])
    m = read_measurements(path)
    assert m.sigma.tolist() == [[1e-5, 2e-5, 3e-5]]


def test_reads_10k_rows_exactly(tmp_path):
    g = torch.Generator().manual_seed(0)
    q = (torch.rand(10_000, 6, generator=g, dtype=torch.float64) - 0.5) * 6
    p = torch.rand(10_000, 3, generator=g, dtype=torch.float64) + 1.0
    path = tmp_path / "big.csv"
    write_measurements(path, Measurements(q=q, p=p, t=torch.arange(10_000, dtype=torch.float64)))
    m = read_measurements(path, dof=6)
    assert torch.equal(m.q, q) and torch.equal(m.p, p) and torch.equal(m.t, torch.arange(10_000, dtype=torch.float64))


# --------------------------------------------------------------------------- header problems


def test_empty_file(tmp_path):
    path = write(tmp_path, [""])
    err = expect_error(path, line=None, column=None)
    assert "empty" in str(err)


def test_comments_only_file_has_no_header(tmp_path):
    path = write(tmp_path, ["# robot: ur5", "# nothing else"])
    err = expect_error(path, line=None, column=None)
    assert "header" in str(err)


def test_missing_position_column(tmp_path):
    path = write(tmp_path, ["# c", "q1,q2,x,y", "0.1,0.2,1.0,2.0"])
    expect_error(path, line=2, column="z")


def test_missing_all_positions_when_required(tmp_path):
    path = write(tmp_path, ["q1,q2", "0.1,0.2"])
    err = expect_error(path, line=1, column="x")
    assert "'y'" in str(err) and "'z'" in str(err)


def test_partial_positions_are_an_error_even_when_not_required(tmp_path):
    path = write(tmp_path, ["q1,q2,x,y", "0.1,0.2,1.0,2.0"])
    expect_error(path, line=1, column="z", require_positions=False)


def test_partial_sigma_is_an_error(tmp_path):
    path = write(tmp_path, [HEADER + ",sx,sz", GOOD_ROWS[0] + ",1e-5,1e-5"])
    expect_error(path, line=1, column="sy")


def test_joint_columns_must_be_contiguous(tmp_path):
    path = write(tmp_path, ["# c", "# d", "q1,q3,x,y,z", "0.1,0.3,1,2,3"])
    err = expect_error(path, line=3, column="q2")
    assert "'q2'" in str(err)


def test_no_joint_columns(tmp_path):
    path = write(tmp_path, ["x,y,z", "1,2,3"])
    expect_error(path, line=1, column="q1")


def test_joint_column_with_leading_zero(tmp_path):
    path = write(tmp_path, ["q01,x,y,z", "0.1,1,2,3"])
    expect_error(path, line=1, column="q01")


def test_case_mismatch_gets_a_hint(tmp_path):
    path = write(tmp_path, ["q1,X,y,z", "0.1,1,2,3"])
    err = expect_error(path, line=1, column="x")
    assert err.hint and "case-sensitive" in err.hint and "'X'" in err.hint


def test_duplicate_header_names(tmp_path):
    path = write(tmp_path, ["# c", "q1,q2,x,y,q2,z", "0.1,0.2,1,2,0.2,3"])
    err = expect_error(path, line=2, column="q2")
    assert "duplicate" in str(err)


def test_empty_header_name(tmp_path):
    path = write(tmp_path, ["q1,x,y,z,", "0.1,1,2,3,"])
    err = expect_error(path, line=1, column=None)
    assert "column 5" in str(err)


def test_semicolon_separated_file_gets_a_hint(tmp_path):
    path = write(tmp_path, ["q1;x;y;z", "0,1;1;2;3"])
    err = expect_error(path, line=1, column=None)
    assert "comma-separated" in err.hint


@pytest.mark.parametrize(
    "robot_name, expected",
    [
        ("ur5", "file has 7 joint columns (q1..q7) but robot 'ur5' has 6 joints"),
        (None, "file has 7 joint columns (q1..q7) but 6 joints are expected"),
    ],
)
def test_too_many_joint_columns(tmp_path, robot_name, expected):
    header = ",".join(f"q{k}" for k in range(1, 8)) + ",x,y,z"
    path = write(tmp_path, ["# robot: ur5", header, ",".join(["0.1"] * 7) + ",1,2,3"])
    err = expect_error(path, line=2, column="q7", dof=6, robot_name=robot_name)
    assert expected in str(err)


def test_too_few_joint_columns(tmp_path):
    path = write(tmp_path, [HEADER, GOOD_ROWS[0]])
    err = expect_error(path, line=1, column="q4", dof=6, robot_name="ur5")
    assert "file has 3 joint columns (q1..q3) but robot 'ur5' has 6 joints" in str(err)


# --------------------------------------------------------------------------- cell problems


def test_empty_cell(tmp_path):
    path = write(tmp_path, ["# c", HEADER, GOOD_ROWS[0], "0.1,0.2,,1.0,2.0,3.0"])
    err = expect_error(path, line=4, column="q3")
    assert "empty" in str(err)


@pytest.mark.parametrize("cell", ["abc", "1,5e-3x", "1_000", "0x10", "--1"])
def test_non_numeric_value(tmp_path, cell):
    path = write(tmp_path, [HEADER, GOOD_ROWS[0], GOOD_ROWS[1], f'0.1,0.2,0.3,1.0,"{cell}",3.0'])
    err = expect_error(path, line=4, column="y")
    assert cell in str(err)


@pytest.mark.parametrize("cell, word", [("nan", "NaN"), ("NaN", "NaN"), ("inf", "infinite"), ("-Infinity", "infinite")])
def test_nan_and_inf(tmp_path, cell, word):
    path = write(tmp_path, ["# c", "", HEADER, GOOD_ROWS[0], f"0.1,0.2,0.3,1.0,2.0,{cell}"])
    err = expect_error(path, line=5, column="z")
    assert word in str(err)


def test_first_bad_cell_in_file_order_wins(tmp_path):
    # NaN on line 3 comes before the non-numeric value on line 4.
    path = write(tmp_path, [HEADER, GOOD_ROWS[0], "0.1,0.2,0.3,nan,2,3", "a,0.2,0.3,1,2,3"])
    expect_error(path, line=3, column="x")


def test_large_finite_values_are_not_mistaken_for_inf(tmp_path):
    # The sum of the row overflows to inf: the slow path must find nothing wrong.
    path = write(tmp_path, ["q1,x,y,z,big1,big2", "0.1,1,2,3,1e308,1e308"])
    m = read_measurements(path)
    assert m.extra["big1"].item() == 1e308


def test_non_numeric_extra_column(tmp_path):
    path = write(tmp_path, [HEADER + ",label", GOOD_ROWS[0] + ",3", GOOD_ROWS[1] + ",home"])
    expect_error(path, line=3, column="label")


def test_comment_after_header_is_an_error_with_hint(tmp_path):
    path = write(tmp_path, [HEADER, GOOD_ROWS[0], "# late comment"])
    err = expect_error(path, line=3, column=None)
    assert "before the header" in err.hint


def test_row_with_too_few_cells(tmp_path):
    path = write(tmp_path, [HEADER, GOOD_ROWS[0], "0.1,0.2,0.3,1.0"])
    expect_error(path, line=3, column="y")


def test_row_with_too_many_cells_hints_at_decimal_comma(tmp_path):
    path = write(tmp_path, [HEADER, GOOD_ROWS[0], "0,1,0.2,0.3,1.0,2.0,3.0"])
    err = expect_error(path, line=3, column=None)
    assert "7 values" in str(err) and "'z'" in str(err)
    assert "decimal point" in err.hint


def test_unterminated_quote(tmp_path):
    path = write(tmp_path, [HEADER, GOOD_ROWS[0], '0.1,"0.2,0.3,1.0,2.0,3.0', GOOD_ROWS[1]])
    expect_error(path, line=3, column=None)


def test_not_utf8(tmp_path):
    path = tmp_path / "latin1.csv"
    path.write_bytes("# operator: Jos\xe9\nq1,x,y,z\n0.1,1,2,3\n".encode("latin-1"))
    expect_error(path, line=1, column=None)


def test_missing_file(tmp_path):
    path = tmp_path / "nope.csv"
    expect_error(path, line=None, column=None)


# --------------------------------------------------------------------------- value problems


@pytest.mark.parametrize("value", ["0", "-1e-5", "0.0"])
def test_sigma_must_be_positive(tmp_path, value):
    path = write(
        tmp_path, [HEADER + ",sx,sy,sz", GOOD_ROWS[0] + ",1e-5,1e-5,1e-5", GOOD_ROWS[1] + f",1e-5,{value},1e-5"]
    )
    expect_error(path, line=3, column="sy")


def test_t_must_be_non_decreasing(tmp_path):
    path = write(tmp_path, ["# c", HEADER + ",t", GOOD_ROWS[0] + ",0.0", GOOD_ROWS[1] + ",2.0", GOOD_ROWS[2] + ",1.5"])
    err = expect_error(path, line=5, column="t")
    assert "line 4" in str(err)  # names the earlier row too


def test_too_few_poses(tmp_path):
    rows = [GOOD_ROWS[k % 3] for k in range(12)]
    path = write(tmp_path, [HEADER, *rows])
    err = expect_error(path, line=None, column=None, min_poses=30, purpose="the geometric fit")
    assert "file has 12 poses, at least 30 are needed for the geometric fit" in str(err)


def test_header_only_file_has_no_poses(tmp_path):
    path = write(tmp_path, ["# c", HEADER])
    err = expect_error(path, line=None, column=None)
    assert "file has 0 poses" in str(err)


def test_joint_limits_violation_names_line_and_column(tmp_path):
    limits = torch.tensor([[-1.0, 1.0], [-0.5, 0.5], [-2.0, 2.0]], dtype=torch.float64)
    path = write(tmp_path, ["# c", HEADER, GOOD_ROWS[0], "0.1,0.2,2.5,1,2,3", "0.1,0.7,0.3,1,2,3"])
    err = expect_error(path, line=4, column="q3", joint_limits=limits, robot_name="ur5")
    assert "ur5" in str(err) and "2.5" in str(err)


def test_joint_limits_tolerate_rounding_at_the_boundary(tmp_path):
    limits = torch.tensor([[-1.0, 1.0]], dtype=torch.float64)
    path = write(tmp_path, ["q1,x,y,z", f"{1.0 + 1e-13!r},1,2,3", "-1.0,1,2,3"])
    read_measurements(path, joint_limits=limits)
    path = write(tmp_path, ["q1,x,y,z", "1.0,1,2,3", f"{-1.0 - 1e-10!r},1,2,3"])
    expect_error(path, line=3, column="q1", joint_limits=limits)


def test_joint_limits_apply_after_degree_conversion(tmp_path):
    limits = torch.tensor([[-math.pi, math.pi]], dtype=torch.float64)
    path = write(tmp_path, ["q1,x,y,z", "179.0,1,2,3", "181.0,1,2,3"])
    err = expect_error(path, line=3, column="q1", joint_limits=limits, angle_unit="deg")
    assert "181 deg" in str(err)


def test_joint_limits_count_must_match_file(tmp_path):
    limits = torch.zeros(6, 2, dtype=torch.float64)
    path = write(tmp_path, [HEADER, GOOD_ROWS[0]])
    expect_error(path, line=1, column="q4", joint_limits=limits)


def test_joint_limits_of_wrong_shape_or_dtype(tmp_path):
    path = write(tmp_path, [HEADER, GOOD_ROWS[0]])
    with pytest.raises(ShapeError):
        read_measurements(path, dof=3, joint_limits=torch.zeros(6, 2, dtype=torch.float64))
    with pytest.raises(ShapeError, match="float32"):
        read_measurements(path, dof=3, joint_limits=torch.zeros(3, 2, dtype=torch.float32))


# --------------------------------------------------------------------------- units


@pytest.mark.parametrize(
    "kwargs, valid", [({"length_unit": "cm"}, "'m', 'mm'"), ({"angle_unit": "grad"}, "'rad', 'deg'")]
)
def test_unknown_unit_lists_valid_values(tmp_path, kwargs, valid):
    path = write(tmp_path, [HEADER, GOOD_ROWS[0]])
    with pytest.raises(OptionError, match=valid):
        read_measurements(path, **kwargs)


def test_mm_and_deg_files_give_the_same_si_tensors(tmp_path):
    g = torch.Generator().manual_seed(1)
    q = (torch.rand(50, 6, generator=g, dtype=torch.float64) - 0.5) * 6.0
    p = torch.rand(50, 3, generator=g, dtype=torch.float64) * 2.0 + 0.5
    sigma = torch.rand(50, 3, generator=g, dtype=torch.float64) * 1e-4 + 1e-5
    si = Measurements(q=q, p=p, sigma=sigma)
    si_path = tmp_path / "si.csv"
    write_measurements(si_path, si)
    other = Measurements(q=torch.rad2deg(q), p=p * 1000.0, sigma=sigma * 1000.0)
    other_path = tmp_path / "mm_deg.csv"
    write_measurements(other_path, other)

    a = read_measurements(si_path, dof=6)
    b = read_measurements(other_path, dof=6, length_unit="mm", angle_unit="deg")
    # The unit conversion costs at most a few ulps.
    torch.testing.assert_close(b.q, a.q, rtol=4e-16, atol=4e-16)
    torch.testing.assert_close(b.p, a.p, rtol=4e-16, atol=0)
    torch.testing.assert_close(b.sigma, a.sigma, rtol=4e-16, atol=0)


def test_mm_conversion_is_correctly_rounded_for_short_decimals(tmp_path):
    a = read_measurements(write(tmp_path, ["q1,x,y,z", "0.5,1.2345,0.0625,-0.7"], name="m.csv"))
    b = read_measurements(write(tmp_path, ["q1,x,y,z", "0.5,1234.5,62.5,-700"], name="mm.csv"), length_unit="mm")
    assert torch.equal(a.p, b.p)


def test_positions_in_mm_declared_as_m(tmp_path):
    path = write(tmp_path, [HEADER, "0.1,0.2,0.3,1500.0,200.0,800.0", "0.1,0.2,0.3,1400.0,-900.0,700.0"])
    err = expect_error(path, line=2, column="x")
    assert "millimetres" in str(err) and "--length-unit mm" in err.hint


def test_positions_in_m_declared_as_mm(tmp_path):
    path = write(tmp_path, [HEADER, *GOOD_ROWS])
    err = expect_error(path, line=2, column="x", length_unit="mm")
    assert "metres" in str(err) and "--length-unit m" in err.hint


def test_angles_in_deg_declared_as_rad(tmp_path):
    path = write(tmp_path, ["# c", HEADER, GOOD_ROWS[0], "10.0,-45.0,90.0,1,2,3", "0,0,180,1,2,3"])
    err = expect_error(path, line=4, column="q1")
    assert "--angle-unit deg" in err.hint


def test_full_turn_in_rad_is_accepted(tmp_path):
    path = write(tmp_path, ["q1,x,y,z", f"{2 * math.pi!r},1,2,3", f"{-2 * math.pi!r},1,2,3"])
    assert read_measurements(path).n == 2


def test_sigma_in_mm_declared_as_m(tmp_path):
    path = write(tmp_path, [HEADER + ",sx,sy,sz", GOOD_ROWS[0] + ",0.005,0.02,0.03", GOOD_ROWS[1] + ",0.02,0.02,0.02"])
    err = expect_error(path, line=2, column="sy")
    assert "--length-unit mm" in err.hint


def test_unit_mix_up_is_reported_before_joint_limits(tmp_path):
    limits = torch.tensor([[-math.pi, math.pi]] * 3, dtype=torch.float64)
    path = write(tmp_path, [HEADER, "10,20,30,1,2,3"])
    err = expect_error(path, line=2, column="q1", joint_limits=limits)
    assert "--angle-unit deg" in err.hint


# --------------------------------------------------------------------------- writing


def random_measurements(n=40, dof=6, seed=2, **overrides):
    g = torch.Generator().manual_seed(seed)

    def r(*shape):
        return torch.randn(*shape, generator=g, dtype=torch.float64)

    q = r(n, dof)
    q[0, 0] = -0.0
    q[1, 1] = 5e-324  # smallest subnormal
    q[2, 1] = 1.0 / 3.0
    fields = dict(
        q=q,
        p=r(n, 3) + torch.tensor([2.0, 0.0, 1.0], dtype=torch.float64),
        t=torch.cumsum(r(n).abs(), 0),
        temperature=20 + r(n),
        sigma=r(n, 3).abs() * 1e-5 + 1e-6,
        meta={"robot": "ur5", "tracker": "AT960 #3: front"},
        extra={"pose_id": torch.arange(n, dtype=torch.float64), "load_kg": r(n)},
    )
    fields.update(overrides)
    return Measurements(**fields)


def assert_same(a: Measurements, b: Measurements):
    for name in ("q", "p", "t", "temperature", "sigma"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            # Bit-exact, including the sign of zero.
            assert torch.equal(x.view(torch.int64), y.view(torch.int64)), name
    assert list(a.extra) == list(b.extra)
    for k in a.extra:
        assert torch.equal(a.extra[k].view(torch.int64), b.extra[k].view(torch.int64)), k
    assert a.meta == b.meta


def test_round_trip_is_bit_exact(tmp_path):
    m = random_measurements()
    path = tmp_path / "out.csv"
    write_measurements(path, m)
    back = read_measurements(path, dof=6)
    assert_same(m, back)
    assert back.lines == tuple(range(4, 44))  # two meta lines and the header come first
    header = path.read_text().splitlines()[2]
    assert header == "q1,q2,q3,q4,q5,q6,x,y,z,t,temperature,sx,sy,sz,pose_id,load_kg"


def test_round_trip_without_positions(tmp_path):
    m = random_measurements(p=None, sigma=None, meta={})
    path = tmp_path / "out.csv"
    write_measurements(path, m)
    assert path.read_text().splitlines()[0].startswith("q1,")
    back = read_measurements(path, require_positions=False)
    assert back.p is None
    assert_same(m, back)


def test_write_meta_is_merged_over_the_measurements_meta(tmp_path):
    path = tmp_path / "out.csv"
    write_measurements(path, random_measurements(), meta={"robot": "ur10", "split": "train"})
    assert read_measurements(path).meta == {"robot": "ur10", "tracker": "AT960 #3: front", "split": "train"}


def test_write_meta_that_cannot_be_written(tmp_path):
    with pytest.raises(MeasurementFileError, match="meta"):
        write_measurements(tmp_path / "out.csv", random_measurements(), meta={"note": "two\nlines"})
    assert not (tmp_path / "out.csv").exists()


def test_write_selected_columns(tmp_path):
    m = random_measurements(n=3, dof=2)
    path = tmp_path / "out.csv"
    write_measurements(path, m, meta={}, columns=["x", "y", "z", "q2", "q1", "t"])
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    assert lines[0] == "x,y,z,q2,q1,t"
    back = read_measurements(path)
    assert torch.equal(back.q, m.q) and torch.equal(back.p, m.p) and back.sigma is None
    with pytest.raises(OptionError, match="'w'"):
        write_measurements(path, m, columns=["q1", "w"])


def test_write_refuses_non_finite_values(tmp_path):
    m = random_measurements(n=5, dof=2, meta={})
    m.p[3, 1] = float("nan")
    with pytest.raises(MeasurementFileError) as info:
        write_measurements(tmp_path / "out.csv", m)
    assert info.value.line == 5 and info.value.column == "y"
    assert not (tmp_path / "out.csv").exists()


def test_write_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "out.csv"
    m = random_measurements()
    calls = 0
    real = measurements_module._format_row

    def failing(values):
        nonlocal calls
        calls += 1
        if calls == 3:
            raise RuntimeError("disk on fire")
        return real(values)

    monkeypatch.setattr(measurements_module, "_format_row", failing)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_measurements(path, m)
    assert calls == 3
    assert os.listdir(tmp_path) == []  # neither the target nor a temporary file is left

    # An existing file survives a failed rewrite untouched.
    path.write_text("old content\n")
    calls = 0
    with pytest.raises(RuntimeError):
        write_measurements(path, m)
    assert path.read_text() == "old content\n"
    assert os.listdir(tmp_path) == ["out.csv"]


def test_write_into_missing_directory(tmp_path):
    """The folder is made, as every command's --out makes it; a path under a file cannot be written."""
    write_measurements(tmp_path / "missing" / "out.csv", random_measurements())
    assert read_measurements(tmp_path / "missing" / "out.csv").n == random_measurements().n
    (tmp_path / "a_file").write_text("x\n")
    with pytest.raises(MeasurementFileError, match="cannot write"):
        write_measurements(tmp_path / "a_file" / "out.csv", random_measurements())


# --------------------------------------------------------------------------- the dataclass


def test_subset_and_with_positions(tmp_path):
    path = tmp_path / "out.csv"
    write_measurements(path, random_measurements(n=10))
    m = read_measurements(path)
    s = m.subset(torch.tensor([7, 2]))
    assert s.n == 2 and s.lines == (m.lines[7], m.lines[2])
    assert torch.equal(s.q, m.q[[7, 2]]) and torch.equal(s.extra["pose_id"], m.extra["pose_id"][[7, 2]])
    assert s.source == m.source and s.meta == m.meta
    assert m.subset(slice(1, 4)).lines == m.lines[1:4]
    mask = torch.zeros(10, dtype=torch.bool)
    mask[[1, 5]] = True
    assert m.subset(mask).lines == (m.lines[1], m.lines[5])

    p = torch.zeros(10, 3, dtype=torch.float64)
    moved = m.with_positions(p)
    assert torch.equal(moved.p, p) and moved.lines == m.lines and m.p is not p
    assert m.with_positions(None).p is None
    with pytest.raises(ShapeError, match=r"\(10, 3\)"):
        m.with_positions(torch.zeros(9, 3, dtype=torch.float64))


def test_measurements_validates_shapes_and_dtypes():
    q = torch.zeros(4, 6, dtype=torch.float64)
    with pytest.raises(ShapeError, match="float64"):
        Measurements(q=q.float())
    with pytest.raises(ShapeError, match="sigma"):
        Measurements(q=q, sigma=torch.ones(4, 2, dtype=torch.float64))
    with pytest.raises(ShapeError, match="lines"):
        Measurements(q=q, lines=(1, 2))
    with pytest.raises(ShapeError, match="'x'"):
        Measurements(q=q, extra={"x": torch.zeros(4, dtype=torch.float64)})
    assert Measurements(q=q).lines == (2, 3, 4, 5)
