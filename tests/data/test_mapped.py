"""convert --map: the four layouts of issue 38 written from simulated campaigns and imported with one command and a
MAP of at most 15 lines each, back to the campaign's numbers; bad input named by file, line and column."""

import math

import numpy as np
import pytest
import torch
import yaml
from _cli import cli_simulate

import torchcal
from torchcal.cli import main
from torchcal.robot import transforms as tf

DEG = 180 / math.pi


def convert(map_text, inputs, out, tmp_path):
    assert len(map_text.strip().splitlines()) <= 15
    (tmp_path / "map.yaml").write_text(map_text, encoding="utf-8")
    return main(["convert", "--map", str(tmp_path / "map.yaml"), *map(str, inputs), "--out", str(out), "--quiet"])


def campaign(tmp_path, *options, robot="ur5"):
    assert cli_simulate(tmp_path / "sim", "--poses", "12", "--test-poses", "2", *options, robot=robot) == 0
    return torchcal.read_measurements(tmp_path / "sim" / "train.csv")


def _close(a, b, tol=1e-12):
    assert a.shape == b.shape and float((a - b).abs().max()) < tol


def test_a_joints_file_and_one_points_file_per_reflector(tmp_path):
    m = campaign(tmp_path, "--probes", "3")
    names = m.probe_names
    q = m.q[m.probe == 0]
    for k in range(3):  # simulate measures every pose with each reflector
        assert torch.equal(m.q[m.probe == k], q)
    np.savetxt(tmp_path / "joints.txt", (q * DEG).numpy(), fmt="%.17g")  # degrees, spaces, no header
    for k in range(3):
        np.savetxt(tmp_path / f"points_{k}.txt", (m.p[m.probe == k] * 1e3).numpy(), fmt="%.17g")  # mm
    map_text = f"""# joints [deg] in one file, the points [mm, tracker frame] one file per reflector
read: {{delimiter: whitespace, header: false}}
units: {{length: mm, angle: deg}}
joints: {{input: 1, columns: 1-6}}
position: {{input: [2, 3, 4], columns: 1-3}}
probe: [{", ".join(names)}]
"""
    inputs = [tmp_path / "joints.txt", *(tmp_path / f"points_{k}.txt" for k in range(3))]
    assert convert(map_text, inputs, tmp_path / "a.csv", tmp_path) == 0
    out = torchcal.read_measurements(tmp_path / "a.csv")
    assert out.probe_names == names
    for k in range(3):
        _close(out.q[out.probe == k], q)
        _close(out.p[out.probe == k], m.p[m.probe == k])


@pytest.mark.parametrize("suffix", [".txt", ".mat"])
def test_b_matlab_rows_of_joints_torques_and_a_4x4_pose(tmp_path, suffix):
    m = campaign(tmp_path, "--orientation", "0.01", robot="panda")
    R = tf.so3_exp(m.r)
    T = torch.cat([torch.cat([R, m.p.unsqueeze(-1) * 1e3], -1), torch.tensor([[[0.0, 0, 0, 1]]]).expand(m.n, 1, 4)], 1)
    tau = torch.randn(m.n, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rows = torch.cat([m.q, tau, T.reshape(m.n, 16)], 1).numpy()
    if suffix == ".txt":
        np.savetxt(
            tmp_path / "data.txt", rows, fmt="%.17g", header="q(1:7) tau(1:7) T(4x4 row-major, mm)", comments="% "
        )
    else:
        from scipy.io import savemat

        savemat(tmp_path / "data.mat", {"campaign": rows})
    map_text = """# rows: 7 joints [rad], 7 torques [N m], the pose 4x4 row-major [mm]
read: {comment: "%"}
units: {length: mm}
joints: 1-7
matrix: 15-30
extra: {tau: 8-14}
"""
    assert convert(map_text, [tmp_path / f"data{suffix}"], tmp_path / "b.csv", tmp_path) == 0
    out = torchcal.read_measurements(tmp_path / "b.csv")
    _close(out.q, m.q)
    _close(out.p, m.p)
    _close(tf.so3_exp(out.r), R, 1e-12)
    _close(torch.stack([out.extra[f"tau{k + 1}"] for k in range(7)], 1), tau)
    if suffix == ".txt":  # the same poses written column-major: refused on the first row, nothing written
        rows[:, 14:30] = T.transpose(-1, -2).reshape(m.n, 16).numpy()
        np.savetxt(tmp_path / "cm.txt", rows, fmt="%.17g", comments="% ")
        assert convert(map_text, [tmp_path / "cm.txt"], tmp_path / "cm.csv", tmp_path) == 2
        assert not (tmp_path / "cm.csv").exists()


def test_one_file_per_station_each_with_its_own_joints(tmp_path, capsys):
    """own: two vendor files, each one station's joints and points. Read with one joints input, the second
    station's rows took the first file's joints without a word; that is refused now, and ``joints: {input: [1, 2]}``
    reads each file's own."""
    m = campaign(tmp_path, "--stations", "2")
    for k in range(2):
        rows = (m.station == k).nonzero()[:, 0]
        body = torch.cat([m.q[rows] * DEG, m.p[rows] * 1e3], 1).tolist()
        text = "A1;A2;A3;A4;A5;A6;X;Y;Z\n" + "".join(";".join(f"{v:.17g}" for v in r) + "\n" for r in body)
        (tmp_path / f"s{k + 1}.csv").write_text(text, encoding="utf-8")
    files = [tmp_path / "s1.csv", tmp_path / "s2.csv"]
    one = """read: {delimiter: ";"}
units: {length: mm, angle: deg}
joints: {columns: [A1, A2, A3, A4, A5, A6]}
position: {input: [1, 2], columns: [X, Y, Z]}
station: [S1, S2]
"""
    assert convert(one, files, tmp_path / "one.csv", tmp_path) == 2 and not (tmp_path / "one.csv").exists()
    assert "has its own joint columns A1, A2, A3, A4, A5, A6" in capsys.readouterr().err
    own = one.replace("joints: {columns:", "joints: {input: [1, 2], columns:")
    assert convert(own, files, tmp_path / "own.csv", tmp_path) == 0
    out = torchcal.read_measurements(tmp_path / "own.csv")
    order = torch.cat([(m.station == k).nonzero()[:, 0] for k in range(2)])
    _close(out.q, m.q[order], 1e-12)
    _close(out.p, m.p[order], 1e-12)
    assert out.station_names == ("S1", "S2") and torch.equal(out.station, m.station[order])
    swapped = own.replace("position: {input: [1, 2]", "position: {input: [2, 1]")
    assert convert(swapped, files, tmp_path / "sw.csv", tmp_path) == 2 and not (tmp_path / "sw.csv").exists()


def test_c_yaml_with_one_block_per_placement(tmp_path):
    m = campaign(tmp_path, "--stations", "2")
    blocks = [
        {"name": name, "poses": [{"q": (m.q[i] * DEG).tolist(), "p": (m.p[i] * 1e3).tolist()} for i in
                                 (m.station == k).nonzero()[:, 0].tolist()]}
        for k, name in enumerate(m.station_names)
    ]  # fmt: skip
    (tmp_path / "campaign.yaml").write_text(yaml.safe_dump({"placements": blocks}), encoding="utf-8")
    map_text = """read: {blocks: placements, rows: poses}
units: {length: mm, angle: deg}
station: {block: name}
joints: q
position: p
"""
    assert convert(map_text, [tmp_path / "campaign.yaml"], tmp_path / "c.csv", tmp_path) == 0
    out = torchcal.read_measurements(tmp_path / "c.csv")
    assert out.station_names == m.station_names
    order = torch.cat([(m.station == k).nonzero()[:, 0] for k in range(len(m.station_names))])
    _close(out.q, m.q[order])
    _close(out.p, m.p[order])
    assert torch.equal(out.station, m.station[order])


def test_d_controller_csv_in_degrees_with_signs_offsets_and_its_own_order(tmp_path):
    m = campaign(tmp_path)
    sign = torch.tensor([1.0, -1, -1, 1, 1, -1], dtype=torch.float64)
    offset = torch.tensor([0.0, -90, 0, -90, 0, 180], dtype=torch.float64)  # deg
    readings = sign * (m.q * DEG - offset)  # model joint = sign * reading + offset
    order = [2, 0, 1, 5, 3, 4]  # the controller's file lists A3, A1, A2, A6, A4, A5
    lines = ["A3;A1;A2;A6;A4;A5;X;Y;Z;Temp"]
    for i in range(m.n):
        cells = [f"{float(readings[i, j]):.17g}" for j in order] + [f"{float(v):.17g}" for v in m.p[i] * 1e3]
        lines.append(";".join(c.replace(".", ",") for c in [*cells, f"{21.5 + i / 10:.2f}"]))
    (tmp_path / "controller.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    map_text = """read: {delimiter: ";", decimal: ","}
units: {length: mm, angle: deg}
joints: {columns: [A1, A2, A3, A4, A5, A6], sign: [1, -1, -1, 1, 1, -1], offset: [0, -90, 0, -90, 0, 180]}
position: [X, Y, Z]
extra: {temperature: Temp}
"""
    assert convert(map_text, [tmp_path / "controller.csv"], tmp_path / "d.csv", tmp_path) == 0
    out = torchcal.read_measurements(tmp_path / "d.csv")
    _close(out.q, m.q)
    _close(out.p, m.p)
    _close(out.temperature, torch.tensor([21.5 + i / 10 for i in range(m.n)], dtype=torch.float64), 1e-9)


def test_bad_input_names_file_line_and_column_and_writes_nothing(tmp_path, capsys):
    (tmp_path / "data.csv").write_text("J1,J2,X,Y,Z\n1,2,3,4,5\n1,two,3,4,5\n", encoding="utf-8")
    good = "joints: [J1, J2]\nposition: [X, Y, Z]\n"
    cases = [
        (good, "data.csv, line 3, column 'J2': 'two' is not a finite number"),
        ("joints: [J1, J2]\nposition: [X, Y, W]\n", "map.yaml, line 2: position.columns: 'W' is no column of"),
        ("joints: [J1, J2]\npositions: [X, Y, Z]\n", "map.yaml, line 2, column 'positions': unknown key"),
        ("joints: {columns: [J1, J2], sign: [1, 2]}\n", "joints.sign must list 2 signs"),
        ("joints: [J1, J2]\nposition: {input: 2, columns: 1-3}\n", "'position' reads input 2"),
        ("joints: [J1, J2]\nposition: [X, Y, Z]\nextra: {x: 1}\n", "line 3, column 'x': extra: 'x' is a column of"),
        ("read: {comment: 5}\njoints: [J1, J2]\n", "line 1, column 'comment': read.comment = 5"),
        ("joints: [J1, J2]\nposition: [X, Y, Z]\nprobe: {column: 1-2}\n", "'probe.column' names 2 columns"),
    ]
    for k, (map_text, message) in enumerate(cases):
        if k == 1:  # the other errors on a file whose cells are all numbers
            (tmp_path / "data.csv").write_text("J1,J2,X,Y,Z\n1,2,3,4,5\n1,2,3,4,5\n", encoding="utf-8")
        assert convert(map_text, [tmp_path / "data.csv"], tmp_path / "out.csv", tmp_path) == 2
        err = capsys.readouterr().err
        assert message in err, err
        assert not (tmp_path / "out.csv").exists()
    assert main(["convert", str(tmp_path / "data.csv"), "--out", str(tmp_path / "out.csv")]) == 2
    assert "one of --map" in capsys.readouterr().err
    # own: each of these was converted, to a file without rows, from the first of two columns named alike, or with
    # a delimiter that is also the decimal mark
    files = {
        "header.csv": ("J1,J2,X,Y,Z\n", good, "header.csv: a header and no rows"),
        "twice.csv": ("J1,J1,X,Y,Z\n1,2,3,4,5\n", good, "column 'J1': joints.columns: the header names column 'J1' 2"),
        "commas.csv": ("J1,J2,X,Y,Z\n1,2,3,4,5\n", 'read: {delimiter: ",", decimal: ","}\n' + good, "cannot be told"),
    }
    for name, (text, map_text, message) in files.items():
        (tmp_path / name).write_text(text, encoding="utf-8")
        assert convert(map_text, [tmp_path / name], tmp_path / "out.csv", tmp_path) == 2
        assert message in capsys.readouterr().err, name
        assert not (tmp_path / "out.csv").exists()


def test_quaternions_in_either_order_and_a_probe_column(tmp_path):
    m = campaign(tmp_path, "--orientation", "0.01")
    angle = m.r.norm(dim=-1, keepdim=True)
    quat = torch.cat([torch.cos(angle / 2), torch.sin(angle / 2) * m.r / angle], -1)  # w, x, y, z
    quat[::2] = -quat[::2]  # q and -q are the same rotation
    names = ["front" if i % 3 else "back" for i in range(m.n)]
    lines = ["J1,J2,J3,J4,J5,J6,X,Y,Z,QX,QY,QZ,QW,Reflector"]
    for i in range(m.n):
        cells = [*m.q[i].tolist(), *m.p[i].tolist(), *quat[i, [1, 2, 3, 0]].tolist()]
        lines.append(",".join(f"{v:.17g}" for v in cells) + f",{names[i]}")
    (tmp_path / "poses.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    map_text = """joints: [J1, J2, J3, J4, J5, J6]
position: [X, Y, Z]
quaternion: {columns: [QX, QY, QZ, QW], order: xyzw}
probe: {column: Reflector}
"""
    assert convert(map_text, [tmp_path / "poses.csv"], tmp_path / "q.csv", tmp_path) == 0
    out = torchcal.read_measurements(tmp_path / "q.csv")
    _close(out.q, m.q)
    _close(out.p, m.p)
    _close(tf.so3_exp(out.r), tf.so3_exp(m.r), 1e-12)
    assert out.probe_names == ("back", "front") and [out.probe_names[int(k)] for k in out.probe] == names
