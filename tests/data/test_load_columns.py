"""The load columns of a measurement file (issue 45): payload [kg], its centre of mass [m, flange frame] and the
measured joint torques tau1..tauN [N m], read, validated (file, line and column named), written back bit for bit and
imported by convert --map's payload: and torques: keys."""

import pytest
import torch

import torchcal
from torchcal.cli import main
from torchcal.data import read_measurements, write_measurements
from torchcal.errors import MeasurementFileError

HEAD = "q1,q2,q3,q4,q5,q6,x,y,z"
ROW = "0.1,-1.2,1.0,0.3,0.2,0.1,1.5,0.2,0.4"


def write(tmp_path, header, *rows):
    path = tmp_path / "m.csv"
    path.write_text("\n".join([header, *rows]) + "\n", encoding="utf-8")
    return path


def test_reads_payload_centre_of_mass_and_torques(tmp_path):
    tau = ",".join(str(v) for v in (0.5, -120.0, -40.0, 3.0, 0.2, 0.0))
    path = write(
        tmp_path,
        HEAD + ",payload,payload_x,payload_y,payload_z," + ",".join(f"tau{k}" for k in range(1, 7)),
        f"{ROW},5,0,0,0.1,{tau}",
        f"{ROW},0,0,0,0.1,{tau}",
    )
    m = read_measurements(path, dof=6)
    assert m.payload.tolist() == [5.0, 0.0]
    assert m.payload_com.tolist() == [[0.0, 0.0, 0.1]] * 2
    assert m.tau.shape == (2, 6) and m.tau[0, 1].item() == -120.0
    write_measurements(tmp_path / "back.csv", m)  # written and read back bit for bit
    back = read_measurements(tmp_path / "back.csv", dof=6)
    assert torch.equal(back.payload, m.payload) and torch.equal(back.tau, m.tau)
    assert torch.equal(back.payload_com, m.payload_com)


def test_files_without_load_columns_have_none(tmp_path):
    m = read_measurements(write(tmp_path, HEAD, ROW), dof=6)
    assert m.payload is None and m.payload_com is None and m.tau is None


def test_centre_of_mass_follows_the_length_unit(tmp_path):
    row = "0.1,-1.2,1.0,0.3,0.2,0.1,1500,200,400"
    path = write(tmp_path, HEAD + ",payload,payload_x,payload_y,payload_z", f"{row},2,10,0,100")
    m = read_measurements(path, dof=6, length_unit="mm")
    assert m.payload_com.tolist() == [[0.01, 0.0, 0.1]] and m.payload.tolist() == [2.0]


@pytest.mark.parametrize(
    ("header", "cells", "line", "column", "says"),  # line 1 is a comment, 2 the header, 3 the row
    [
        (",payload", ",-1", 3, "payload", "a payload is a mass, >= 0"),
        (",payload", ",5000", 3, "payload", "kilograms, not grams"),
        (",payload", ",nan", 3, "payload", "values must be finite"),
        (",payload,payload_x,payload_y", ",1,0,0", 2, "payload_z", "all of payload_x"),
        (",payload_x,payload_y,payload_z", ",0,0,0", 2, "payload", "need the payload column"),
        (",payload,payload_x,payload_y,payload_z", ",1,0,0,50", 3, "payload_z", "beyond 5 m"),
        (",tau1,tau2", ",1,2", 2, "tau3", "one torque per joint"),
        (",tau1,tau3,tau2,tau4,tau5,tau7", ",1,2,3,4,5,6", 2, "tau7", "without gaps"),
        (",tau01,tau2,tau3,tau4,tau5,tau6", ",1,2,3,4,5,6", 2, "tau01", "leading zeros"),
        (",tau1,tau2,tau3,tau4,tau5,tau6", ",1,2e7,3,4,5,6", 3, "tau2", "not a joint torque"),
    ],
)
def test_bad_load_columns_are_named(tmp_path, header, cells, line, column, says):
    path = write(tmp_path, "# a comment\n" + HEAD + header, ROW + cells)
    with pytest.raises(MeasurementFileError) as err:
        read_measurements(path, dof=6)
    assert err.value.line == line and err.value.column == column, str(err.value)
    assert says in str(err.value)


def test_convert_maps_payload_and_torques_by_name(tmp_path):
    text = "A1 A2 A3 A4 A5 A6 X Y Z M T1 T2 T3 T4 T5 T6\n"
    text += "0.1 -1.2 1.0 0.3 0.2 0.1 1500 200 400 5 0.5 -120 -40 3 0.2 0\n"
    (tmp_path / "in.txt").write_text(text, encoding="utf-8")
    common = "read: {delimiter: whitespace}\nunits: {length: mm}\njoints: 1-6\nposition: 7-9\npayload: M\n"
    (tmp_path / "map.yaml").write_text(common + "torques: 11-16\n", encoding="utf-8")
    args = ["convert", "--map", str(tmp_path / "map.yaml"), str(tmp_path / "in.txt"), "--quiet"]
    assert main([*args, "--out", str(tmp_path / "out.csv")]) == 0
    m = torchcal.read_measurements(tmp_path / "out.csv", dof=6)
    assert m.payload.tolist() == [5.0] and m.tau[0].tolist() == [0.5, -120.0, -40.0, 3.0, 0.2, 0.0]
    (tmp_path / "map.yaml").write_text(common + "torques: 11-15\n", encoding="utf-8")  # one short
    assert main([*args, "--out", str(tmp_path / "bad.csv")]) == 2
    assert not (tmp_path / "bad.csv").exists()
