"""Compensation: joints that make the calibrated model put the probe on targets (torchcal.use.compensate, CLI)."""

import math

import pytest
import torch
from _cli import cli_simulate

import torchcal
from torchcal._threads import torch_threads
from torchcal.cli import main
from torchcal.effects import Compliance, Context, CorrectionNet, Drift, LearnedEffect
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.report.urdf import urdf_fk_difference, urdf_gap, urdf_notes
from torchcal.robot import transforms as tf
from torchcal.robot import write_urdf
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.use.compensate import (
    Status,
    compensate,
    configuration_sign,
    model_miss,
    nominal_ik,
    program_targets,
)

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def calibrated_model(seed=0, effects=True):
    """A UR5 with geometry, tracker and lever-arm corrections, joint-2 compliance and a learned field."""
    g = torch.Generator().manual_seed(seed)
    robot = torchcal.load_robot("ur5")
    with torch.no_grad():
        robot.geometry.delta.copy_(
            torch.randn(robot.geometry.delta.shape, generator=g, dtype=F64) * 1e-3 * robot.geometry.mask
        )
        robot.instrument.set_matrix(
            tf.homogeneous(tf.rot_z(torch.tensor(0.7, dtype=F64)), torch.tensor([2.0, -1.0, 0.3], dtype=F64))
        )
        robot.tool.nominal.copy_(torch.tensor([0.01, 0.0, 0.12], dtype=F64))
    if not effects:
        return MeasurementModel(robot, [])
    net = CorrectionNet(6, 29)
    net.reset_parameters(g, gain=2.0)
    field = LearnedEffect(net)
    with torch.no_grad():
        field.scale_(1e-4 / float(net(torch.rand(50, 6, generator=g, dtype=F64)).norm(dim=-1).mean()))
    return MeasurementModel(robot, [Compliance(2, k=2e-6), field])


def poses(robot, n, seed=1):
    g = torch.Generator().manual_seed(seed)
    # away from the stretched elbow and the wrist singularity, where any position is a test of the branch check
    q = (torch.rand(n, 6, generator=g, dtype=F64) * 2 - 1) * math.pi
    q[:, 2] = torch.sign(q[:, 2]) * (0.4 + q[:, 2].abs() * 0.6)
    q[:, 4] = torch.sign(q[:, 4]) * (0.4 + q[:, 4].abs() * 0.6)
    return q


def test_known_answers_reached_to_1e9():
    model = calibrated_model()
    q_true = poses(model.robot, 300)
    with torch.no_grad():
        targets = model(Context(q=q_true))
    g = torch.Generator().manual_seed(3)
    q0 = q_true + torch.randn(q_true.shape, generator=g, dtype=F64) * 2e-3
    res = compensate(model, targets, q0)
    assert res.counts() == {"converged": 300, "limit": 0, "unreachable": 0}
    assert float(res.miss.max()) <= 1e-9
    # checked independently: the model itself, evaluated at the returned joints
    with torch.no_grad():
        assert float((model(Context(q=res.q)) - targets).norm(dim=-1).max()) <= 1e-9
    # the solution nearest the start: never farther from it than the known answer
    assert bool(((res.q - q0).norm(dim=-1) <= (q_true - q0).norm(dim=-1) + 1e-9).all())
    # a target the start already reaches: nothing moves
    res0 = compensate(model, targets, q_true)
    assert torch.allclose(res0.q, q_true, atol=1e-9, rtol=0)


def test_joint_limits_respected_and_reported():
    model = calibrated_model()
    q0 = poses(model.robot, 20)
    with torch.no_grad():
        model.robot.limits.copy_(torch.stack([q0[0] - 1e-4, q0[0] + 1e-4], dim=-1))
        targets = model(Context(q=q0[:1].expand(20, 6).clone()))
    targets = targets + torch.tensor([0.005, 0.0, 0.0], dtype=F64)  # 5 mm off: needs far more than 1e-4 rad
    res = compensate(model, targets, q0[:1].expand(20, 6).clone())
    lo, hi = model.robot.limits[:, 0], model.robot.limits[:, 1]
    assert bool(((res.q >= lo) & (res.q <= hi)).all())
    assert set(res.status) == {Status.LIMIT}
    assert float(res.miss.min()) > 1e-3


def test_out_of_reach_is_named_not_dropped():
    model = calibrated_model()
    q0 = poses(model.robot, 4)
    with torch.no_grad():
        targets = model(Context(q=q0))
    targets[2] = targets[2] + torch.tensor([3.0, 0.0, 0.0], dtype=F64)  # 3 m beyond a 0.9 m arm
    res = compensate(model, targets, q0)
    assert [s.value for s in res.status] == ["converged", "converged", "unreachable", "converged"]
    assert float(res.miss[2]) > 1.0 and res.q.shape == (4, 6)
    with pytest.raises(torchcal.errors.ShapeError, match="not finite"):
        compensate(model, torch.full((2, 3), float("nan"), dtype=F64), q0[:2])


def test_branch_kept_on_1000_campaign_poses_and_fast():
    c = simulate(
        SimConfig(
            robot="ur5",
            poses=1000,
            test_poses=0,
            seed=4,
            effects=[EffectSpec.parse("compliance:2=60um"), EffectSpec.parse("field=0.05mm")],
        )
    )
    model = c.model
    q0 = c.train.q
    compensate(model, c.train.p[:10], q0[:10])  # warm-up
    res = compensate(model, c.train.p, q0)  # the measured points, noise and all, from the read joints
    assert res.counts()["converged"] == 1000
    moved = (res.q - q0).abs().max(dim=-1).values
    for j in (2, 4):  # elbow and wrist: sign of sin q3, sin q5 where the start is not at the singularity
        s0 = torch.sin(q0[:, j])
        assert not bool(((torch.sign(torch.sin(res.q[:, j])) != torch.sign(s0)) & (s0.abs() > 1e-2)).any())
    flips = (configuration_sign(model.robot, res.q) != configuration_sign(model.robot, q0)) & (moved > 0.05)
    assert int(flips.sum()) == 0
    assert float(moved.max()) < 0.05


def test_nominal_ik_start_for_xyz_only_targets():
    model = calibrated_model()
    q_true = poses(model.robot, 8)
    with torch.no_grad():
        targets = model(Context(q=q_true))
    res = compensate(model, targets)
    assert res.counts()["converged"] == 8
    assert float(model_miss(model, res.q, targets).max()) <= 1e-9
    # nominal_ik alone, in the base frame
    robot = model.robot
    with torch.no_grad():
        pb = robot.probe_in_base(q_true)
    q = nominal_ik(robot, pb)
    with torch.no_grad():
        assert float((robot.probe_in_base(q) - pb).norm(dim=-1).max()) <= 1e-8


def test_program_rows_mean_the_nominal_point():
    model = calibrated_model()
    q_prog = poses(model.robot, 10)
    targets = program_targets(model, q_prog)
    res = compensate(model, targets, q_prog)
    assert res.counts()["converged"] == 10
    # the nominal robot (zero corrections) puts the probe for q_prog where the calibrated model puts it for q
    import copy

    nominal = copy.deepcopy(model.robot)
    nominal.geometry.reset()
    with torch.no_grad():
        p_nom = tf.transform_points(
            model.robot.T_tracker_base(), tf.transform_points(nominal(q_prog), model.robot.t_flange_probe())
        )
        assert float((model(Context(q=res.q)) - p_nom).norm(dim=-1).max()) <= 1e-9
    assert float((res.q - q_prog).abs().max()) > 1e-5  # the calibration did change the commands


def test_context_needed_by_effects():
    model = calibrated_model()
    model.add(Drift("temperature", "scale", rates=[2.3e-5], reference=20.0))
    q0 = poses(model.robot, 3)
    temp = torch.tensor([20.0, 22.0, 25.0], dtype=F64)
    with torch.no_grad():
        targets = model(Context(q=q0, temperature=temp))
    with pytest.raises(OptionError, match="'temperature' column"):
        compensate(model, targets, q0)
    res = compensate(model, targets, q0, context={"temperature": temp})
    assert float(model_miss(model, res.q, targets, context={"temperature": temp}).max()) <= 1e-9
    assert res.counts()["converged"] == 3


def test_urdf_gap_and_pk_agree_without_effects(tmp_path):
    pk = pytest.importorskip("pytorch_kinematics")
    model = calibrated_model(effects=False)
    robot = model.robot
    q_true = poses(robot, 20)
    with torch.no_grad():
        targets = model(Context(q=q_true))
    path = write_urdf(robot, tmp_path / "cal.urdf")
    ctx = Context(q=q_true)
    gap = urdf_fk_difference(path, model, ctx)
    assert gap["left_out"] == [] and gap["max_mm"] <= 1e-9
    assert urdf_notes(gap)[0].startswith("The calibration found no effect")
    res = compensate(model, targets, q_true + 1e-3)
    # pytorch-kinematics on the calibrated URDF (its own parser, float32) puts the probe on the targets too
    chain = pk.build_serial_chain_from_urdf(path.read_bytes(), "probe", robot.base_link)
    p_base = chain.forward_kinematics(res.q.float()).get_matrix()[:, :3, 3].double()
    p = tf.transform_points(robot.T_tracker_base().detach(), p_base)
    assert float((p - targets).norm(dim=-1).max()) <= 1e-5
    # pk's own IK on that URDF, for the flange pose compensate chose and from the same start, finds the same joints
    chain = chain.to(dtype=F64)
    goal = chain.forward_kinematics(res.q)
    found = []
    for i in range(len(res.q)):
        ik = pk.PseudoInverseIK(
            chain,
            max_iterations=100,
            retry_configs=(q_true[i] + 1e-3)[None],
            joint_limits=robot.limits,
            early_stopping_any_converged=True,
            pos_tolerance=1e-9,
            rot_tolerance=1e-9,
        )
        found.append(ik.solve(pk.Transform3d(matrix=goal.get_matrix()[i : i + 1])).solutions[0, 0])
    assert float((torch.stack(found) - res.q).abs().max()) <= 1e-5
    # compensate on the URDF read back by torchcal (no effects: the URDF is the whole model) agrees to rounding
    back = torchcal.load_robot(path, tip_link="probe")
    with torch.no_grad():
        back.instrument.set_matrix(robot.T_tracker_base())
    res_back = compensate(back, targets, q_true + 1e-3)
    assert float((res_back.q - res.q).abs().max()) <= 1e-8


def test_urdf_gap_with_effects(tmp_path):
    model = calibrated_model()
    q = poses(model.robot, 50)
    ctx = Context(q=q)
    path = write_urdf(model.robot, tmp_path / "cal.urdf")
    gap, measured = urdf_gap(model, ctx), urdf_fk_difference(path, model, ctx)
    assert gap["left_out"] == ["compliance(joint 2)", "learned"]
    assert gap["rms_mm"] > 1e-3 and abs(gap["rms_mm"] - measured["rms_mm"]) <= 1e-9
    assert abs(gap["max_mm"] - measured["max_mm"]) <= 1e-9
    assert "NOT in this URDF: compliance(joint 2), learned" in urdf_notes(gap)[0]


# ------------------------------------------------------------------------------------------------ CLI
@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A kinematic calibration of a small simulated UR5 campaign (no effects: fast)."""
    d = tmp_path_factory.mktemp("comp")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert cli_simulate(d / "data", "--poses", "120", "--test-poses", "20", "--seed", "2") == 0
        assert (
            main(
                [
                    "calibrate",
                    str(d / "data" / "train.csv"),
                    "--robot",
                    "ur5",
                    "--out",
                    str(d / "run"),
                    "--method",
                    "kinematic",
                    "--quiet",
                ]
            )
            == 0
        )
    finally:
        torch.set_num_threads(before)
    return d


def _read(path):
    import csv

    rows = [r for r in csv.reader(line for line in open(path, encoding="utf-8") if not line.startswith("#"))]
    return rows[0], rows[1:]


def test_cli_round_trip(run_dir, tmp_path, capsys):
    from torchcal.data import read_measurements
    from torchcal.use.rundir import load_model

    test = read_measurements(run_dir / "data" / "test.csv")
    q, p = test.q[:6], test.p[:6]
    far = p[3] + torch.tensor([4.0, 0.0, 0.0], dtype=F64)
    lines = ["q1,q2,q3,q4,q5,q6,x,y,z,label"]
    for i in range(6):
        pt = far if i == 3 else p[i]
        lines.append(",".join(repr(float(v)) for v in [*q[i], *pt]) + f",{10 + i}")
    (tmp_path / "both.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "joints.csv"
    assert main(["compensate", str(run_dir / "run"), str(tmp_path / "both.csv"), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "line 5: unreachable" in err  # the 4th data row, on file line 5, is named
    header, rows = _read(out)
    assert header == [
        "q1",
        "q2",
        "q3",
        "q4",
        "q5",
        "q6",
        "x",
        "y",
        "z",
        *[f"q{k}_program" for k in range(1, 7)],  # the file's joints kept beside the commands
        "label",
        "sx",
        "sy",
        "sz",
        "extrapolation",
        "model",
        "miss",
        "status",
    ]
    assert [r[-1] for r in rows] == ["converged"] * 3 + ["unreachable"] + ["converged"] * 2
    assert [float(r[header.index("label")]) for r in rows] == [10.0, 11.0, 12.0, 13.0, 14.0, 15.0]
    assert torch.equal(_table(out, [f"q{k}_program" for k in range(1, 7)]), q)
    model, _ = load_model(run_dir / "run")
    qc = torch.tensor([[float(v) for v in r[:6]] for r in rows], dtype=F64)
    with torch.no_grad():
        miss = (model(Context(q=qc)) - p).norm(dim=-1)
    assert float(miss[[0, 1, 2, 4, 5]].max()) <= 1e-9
    assert float(rows[3][header.index("miss")]) > 3.0

    # a program: q only means the nominal model's point; x,y,z only starts from the nominal IK
    (tmp_path / "prog.csv").write_text(
        "q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in q) + "\n"
    )
    assert main(["compensate", str(run_dir / "run"), str(tmp_path / "prog.csv"), "--out", str(out), "--quiet"]) == 0
    header, rows = _read(out)
    assert header[-2:] == ["miss", "status"] and all(r[-1] == "converged" for r in rows)
    (tmp_path / "xyz.csv").write_text("x,y,z\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in p) + "\n")
    assert main(["compensate", str(run_dir / "run"), str(tmp_path / "xyz.csv"), "--out", str(out), "--quiet"]) == 0
    assert all(r[-1] == "converged" for r in _read(out)[1])
    # ... or from --start, in degrees and millimetres
    (tmp_path / "xyz_mm.csv").write_text(
        "x,y,z\n" + "\n".join(",".join(repr(float(v) * 1e3) for v in r) for r in p) + "\n"
    )
    (tmp_path / "start.csv").write_text(
        "q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(repr(math.degrees(float(v))) for v in r) for r in q) + "\n"
    )
    assert (
        main(
            [
                "compensate",
                str(run_dir / "run"),
                str(tmp_path / "xyz_mm.csv"),
                "--out",
                str(out),
                "--start",
                str(tmp_path / "start.csv"),
                "--length-unit",
                "mm",
                "--angle-unit",
                "deg",
                "--quiet",
            ]
        )
        == 0
    )
    header, rows = _read(out)
    qs = torch.tensor([[float(v) for v in r[:6]] for r in rows], dtype=F64)  # in the file's units: degrees
    assert "# angle_unit: deg" in out.read_text() and "# length_unit: mm" in out.read_text()
    assert float((torch.deg2rad(qs) - qc).abs()[[0, 1, 2, 4, 5]].max()) <= 1e-6  # the solutions from the file's q
    assert float((_table(out, ["x", "y", "z"]) - p * 1e3).abs().max()) <= 1e-9  # the targets as written, in mm


def test_cli_bad_files(run_dir, tmp_path, capsys):
    run = str(run_dir / "run")
    out = tmp_path / "j.csv"
    cases = {
        "x,y,z\n1.0,0.5,0.2\n1.0,nan,0.3\n": ("line 3", "y"),
        "x,y\n1.0,0.5\n": ("'z'", None),
        "a,b\n1,2\n": ("'q1'", "x, y, z or q1..qN"),
        "q1,q2,q3\n0,0,0\n": ("3 joint columns", None),
    }
    for text, (where, also) in cases.items():
        (tmp_path / "bad.csv").write_text(text)
        assert main(["compensate", run, str(tmp_path / "bad.csv"), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "bad.csv" in err and where in err, err
        if also:
            assert also in err, err
        assert not out.exists()
    (tmp_path / "xyz.csv").write_text("x,y,z\n1.0,0.5,0.2\n1.0,0.4,0.3\n")
    (tmp_path / "start.csv").write_text("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n")
    assert (
        main(["compensate", run, str(tmp_path / "xyz.csv"), "--out", str(out), "--start", str(tmp_path / "start.csv")])
        == 2
    )
    assert "1 start rows for 2 targets" in capsys.readouterr().err
    assert not out.exists()


def test_run_dir_states_what_the_urdf_leaves_out(run_dir):
    import json

    report = json.loads((run_dir / "run" / "report.json").read_text())
    assert report["urdf"]["left_out"] == [] and report["urdf"]["max_mm"] <= 1e-9
    assert "## The calibrated URDF" in (run_dir / "run" / "report.md").read_text()
    head = (run_dir / "run" / "robot_calibrated.urdf").read_text().split("-->")[0]
    assert "no effect beyond geometry" in head


# ------------------------------------------------------------------------------ stations and probes per row
@pytest.fixture(scope="module")
def two_stations(tmp_path_factory):
    """A kinematic calibration of a simulated UR5 cell of two stations and two probes on a nest, with a 6-D probe's
    orientation (issue 34's cell, small)."""
    d = tmp_path_factory.mktemp("two")
    with torch_threads(1):
        assert cli_simulate(d / "sim", "--poses", "80", "--test-poses", "12", "--seed", "1", "--stations", "2",
                            "--probes", "2", "--orientation", "0.01") == 0  # fmt: skip
        cmd = ["calibrate", str(d / "sim" / "train.csv"), "--robot", "ur5", "--out", str(d / "run")]
        assert main([*cmd, "--method", "kinematic", "--quiet"]) == 0
    return d


def _table(path, columns):
    header, rows = _read(path)
    return torch.tensor([[float(r[header.index(c)]) for c in columns] for r in rows], dtype=F64)


Q6 = [f"q{k}" for k in range(1, 7)]


@pytest.mark.slow
def test_cli_each_row_in_its_own_station_and_probe(two_stations, tmp_path):
    """bug before: every row was solved in the first station's frame with the first probe's lever arm (S2 rows
    unreachable by metres, P2 rows by 100 mm) and the columns were dropped from the output."""
    from torchcal.data import read_measurements
    from torchcal.use.rundir import load_model

    run, test = two_stations / "run", two_stations / "sim" / "test.csv"
    out = tmp_path / "j.csv"
    assert main(["compensate", str(run), str(test), "--out", str(out), "--quiet"]) == 0
    header, rows = _read(out)
    data = read_measurements(test)
    assert [r[header.index("station")] for r in rows] == [data.station_names[i] for i in data.station.tolist()]
    assert [r[header.index("probe")] for r in rows] == [data.probe_names[i] for i in data.probe.tolist()]
    assert {r[header.index("station")] for r in rows} == {"S1", "S2"}
    assert all(r[-1] == "converged" for r in rows)
    # checked by the run's full model at each row's own station and probe
    model, _ = load_model(run)
    ctx = Context(q=_table(out, Q6), station=data.station, probe=data.probe)  # the run's order is the file's here
    with torch.no_grad():
        assert float((model(ctx) - data.p).norm(dim=-1).max()) <= 1e-9
    # the column and --station agree: S2's rows without their column, placed by the option
    lines = [ln for ln in test.read_text().splitlines() if not ln.startswith("#")]
    head = lines[0].split(",")
    keep = [i for i, c in enumerate(head) if c != "station"]
    s2 = [ln for ln in lines[1:] if ln.split(",")[head.index("station")] == "S2"]
    (tmp_path / "s2.csv").write_text("\n".join(",".join(ln.split(",")[i] for i in keep) for ln in [lines[0], *s2]))
    out2 = tmp_path / "j2.csv"
    assert (
        main(["compensate", str(run), str(tmp_path / "s2.csv"), "--out", str(out2), "--station", "S2", "--quiet"]) == 0
    )
    in_s2 = [i for i, r in enumerate(rows) if r[header.index("station")] == "S2"]
    assert torch.equal(_table(out2, Q6), _table(out, Q6)[in_s2])
    assert {r[_read(out2)[0].index("station")] for r in _read(out2)[1]} == {"S2"}


@pytest.mark.parametrize(
    ("column", "value", "option", "says"),
    [
        ("station", "S3", None, "station 'S3' is not one of the run's stations (S1, S2)"),
        ("probe", "P7", None, "probe 'P7' is not one of the run's probes (P1, P2)"),
        ("station", "S1", ["--station", "S2"], "station 'S1' conflicts with --station S2"),
        ("probe", "P2", ["--probe", "P1"], "probe 'P2' conflicts with --probe P1"),
    ],
)
def test_cli_a_row_of_a_station_or_probe_the_run_lacks_is_refused(two_stations, tmp_path, capsys, column, value,
                                                                   option, says):  # fmt: skip
    lines = [ln for ln in (two_stations / "sim" / "test.csv").read_text().splitlines() if not ln.startswith("#")]
    k = lines[0].split(",").index(column)
    cells = lines[3].split(",")
    cells[k] = value
    lines[3] = ",".join(cells)
    if option:  # every other row agrees with the option: only line 4 conflicts
        for i in (1, 2, *range(4, len(lines))):
            cells = lines[i].split(",")
            cells[k] = option[1]
            lines[i] = ",".join(cells)
    (tmp_path / "t.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "j.csv"
    cmd = ["compensate", str(two_stations / "run"), str(tmp_path / "t.csv"), "--out", str(out), *(option or [])]
    assert main(cmd) == 2
    err = capsys.readouterr().err
    assert f"t.csv, line 4, column '{column}': {says}" in err, err
    assert not out.exists()


def test_each_pair_takes_its_own_learned_correction(two_stations):
    """compensate_groups solves each row with its station's frame, its probe's lever arm and that pair's learned
    correction: the full model (which dispatches the correction by each row's pair) puts the probe on every target."""
    import copy

    from torchcal.data import read_measurements
    from torchcal.effects.grouped import GroupedCorrection
    from torchcal.use.compensate import compensate_groups
    from torchcal.use.rundir import at_station, load_model

    model, _ = load_model(two_stations / "run")
    model = copy.deepcopy(model)
    g = torch.Generator().manual_seed(5)
    fields = []
    for _ in range(2):  # 0.1 mm fields, one for (S1, P2) and one for (S2, P1); (S1, P1) and (S2, P2) have none
        net = CorrectionNet(6, 8)
        net.reset_parameters(g, gain=2.0)
        field = LearnedEffect(net)
        with torch.no_grad():
            field.scale_(1e-4 / float(net(torch.rand(50, 6, generator=g, dtype=F64)).norm(dim=-1).mean()))
        fields.append(field)
    model.add(GroupedCorrection([(0, 1), (1, 0)], fields))
    data = read_measurements(two_stations / "sim" / "test.csv")
    with torch.no_grad():
        ctx = Context(q=data.q, station=data.station, probe=data.probe)
        targets = model(ctx)
        moved = (targets - MeasurementModel(model.robot, [])(ctx)).norm(dim=-1)
    assert float(moved.min()) == 0.0 and float(moved.max()) > 2e-5  # the pairs differ

    res, _, plain = compensate_groups(
        model, data.station, data.probe, lambda m, rows: (targets[rows], None), data.q, at=at_station
    )
    assert res.counts()["converged"] == data.n
    # rows commanded outside the calibrated region go without the learned correction (compensate_in_region)
    inside = ~plain
    assert int(inside.sum()) >= data.n // 2
    with torch.no_grad():
        hit = model(Context(q=res.q, station=data.station, probe=data.probe))
    assert float((hit - targets).norm(dim=-1)[inside].max()) <= 1e-9
    assert float((res.q - data.q).abs()[inside].max()) <= 1e-6  # the known answer: the rows' own joints


# ------------------------------------------------------------------------------ 6-D compensation
def _with_orientation(model, seed=4):
    g = torch.Generator().manual_seed(seed)
    model.robot.enable_orientation(tf.so3_exp(torch.randn(3, generator=g, dtype=F64)))
    return model


def test_six_d_known_answers_reached_to_1e9():
    """Position and orientation targets of known joints (a 6-joint arm: one solution near the start) are met to 1e-9
    m and rad in the instrument frame; a position-only solve from the same start leaves the tool turned."""
    model = _with_orientation(calibrated_model())
    q_true = poses(model.robot, 200)
    with torch.no_grad():
        ctx = Context(q=q_true)
        targets, R = model(ctx), model.orientation(ctx)
    g = torch.Generator().manual_seed(3)
    q0 = q_true + torch.randn(q_true.shape, generator=g, dtype=F64) * 2e-3
    res = compensate(model, targets, q0, orientations=R)
    assert res.counts()["converged"] == 200
    assert float(res.miss.max()) <= 1e-9 and float(res.miss_angle.max()) <= 1e-9
    assert float((res.q - q_true).abs().max()) <= 1e-7
    with torch.no_grad():  # checked independently, by the model at the returned joints
        R_hit = model.orientation(Context(q=res.q))
    assert float((R_hit - R).abs().max()) <= 1e-9
    free = compensate(model, targets, q0)
    assert free.miss_angle is None and float(free.miss.max()) <= 1e-9
    with torch.no_grad():
        turned = torch.linalg.matrix_norm(model.orientation(Context(q=free.q)) - R)
    assert float(turned.median()) > 1e-4  # the tool left free to turn does turn


def test_six_d_from_nominal_ik_and_refusals():
    model = _with_orientation(calibrated_model(effects=False))
    q_true = poses(model.robot, 20, seed=6)
    with torch.no_grad():
        ctx = Context(q=q_true)
        targets, R = model(ctx), model.orientation(ctx)
    res = compensate(model, targets, None, orientations=R)  # no start: the 6-D nominal IK, nearest the middle
    assert res.counts()["converged"] == 20 and float(res.miss_angle.max()) <= 1e-9
    with pytest.raises(OptionError, match="carries no probe orientation"):
        compensate(calibrated_model(effects=False), targets, q_true, orientations=R)
    with pytest.raises(OptionError, match="orientation_weight"):
        compensate(model, targets, q_true, orientations=R, orientation_weight=0.0)
    with pytest.raises(torchcal.errors.ShapeError, match="orientations"):
        compensate(model, targets, q_true, orientations=R[:3])


def test_cli_six_d_program_keeps_its_joints_and_units(two_stations, tmp_path):
    """Program joints alone, on a run that fitted the probe's orientation: the full pose the nominal model gives them
    is reached (issue 38 item 2), the program's joints are kept beside the commands, the orientation miss is written
    beside the position miss, and degrees in give degrees out; --position-only and a run without orientation solve
    positions only and say so."""
    from torchcal.data import read_measurements
    from torchcal.use.compensate import program_orientations, program_targets
    from torchcal.use.rundir import load_model

    run = two_stations / "run"
    data = read_measurements(two_stations / "sim" / "test.csv")
    rad = "\n".join(",".join(repr(float(v)) for v in r) for r in data.q[:8])
    deg = "\n".join(",".join(repr(math.degrees(float(v))) for v in r) for r in data.q[:8])
    (tmp_path / "prog.csv").write_text(",".join(Q6) + "\n" + rad + "\n")
    (tmp_path / "deg.csv").write_text(",".join(Q6) + "\n" + deg + "\n")
    out, out_deg, free = tmp_path / "j.csv", tmp_path / "jd.csv", tmp_path / "free.csv"
    assert main(["compensate", str(run), str(tmp_path / "prog.csv"), "--out", str(out), "--quiet"]) == 0
    cmd = ["compensate", str(run), str(tmp_path / "deg.csv"), "--out", str(out_deg), "--angle-unit", "deg"]
    assert main([*cmd, "--quiet"]) == 0
    assert main(["compensate", str(run), str(tmp_path / "prog.csv"), "--out", str(free), "--position-only"]) == 0
    header, rows = _read(out)
    assert header[-3:] == ["miss", "miss_angle", "status"] and all(r[-1] == "converged" for r in rows)
    assert "# compensation: position and orientation (the orientation the nominal model gives the program)" in (
        out.read_text()
    )
    q = _table(out, Q6)
    assert torch.equal(_table(out, [f"{c}_program" for c in Q6]), data.q[:8])
    model, _ = load_model(run)  # the first station and probe: the file has no columns
    with torch.no_grad():
        ctx = Context(q=q, station=torch.zeros(8, dtype=torch.long), probe=torch.zeros(8, dtype=torch.long))
        from torchcal.use.rundir import at_station

        at, _, _ = at_station(model, "S1", "P1")
        assert float((model(ctx) - program_targets(at, data.q[:8])).norm(dim=-1).max()) <= 1e-9
        assert float((model.orientation(ctx) - program_orientations(at, data.q[:8])).abs().max()) <= 1e-9
    # degrees in, degrees out: the same commands, the program's joints as written
    assert float((_table(out_deg, Q6) - torch.rad2deg(q)).abs().max()) <= 1e-9
    assert float((_table(out_deg, [f"{c}_program" for c in Q6]) - torch.rad2deg(data.q[:8])).abs().max()) <= 1e-9
    assert "# angle_unit: deg" in out_deg.read_text()
    # --position-only: no orientation miss, the tool turned away from the program's orientation
    header, rows = _read(free)
    assert "miss_angle" not in header and "# compensation: position only (--position-only)" in free.read_text()
    with torch.no_grad():
        ctx = Context(q=_table(free, Q6), station=ctx.station, probe=ctx.probe)
        assert float((model.orientation(ctx) - program_orientations(at, data.q[:8])).abs().max()) > 1e-4


def test_cli_position_only_where_the_run_has_no_orientation(run_dir, tmp_path, capsys):
    from torchcal.data import read_measurements

    data = read_measurements(run_dir / "data" / "test.csv")
    text = "\n".join(",".join(repr(float(v)) for v in r) for r in data.q[:4])
    (tmp_path / "prog.csv").write_text(",".join(Q6) + "\n" + text + "\n")
    out = tmp_path / "j.csv"
    assert main(["compensate", str(run_dir / "run"), str(tmp_path / "prog.csv"), "--out", str(out)]) == 0
    assert "position only (the run has no orientation model" in capsys.readouterr().err
    assert "# compensation: position only (the run has no orientation model" in out.read_text()
    assert "miss_angle" not in _read(out)[0]


def test_six_d_next_to_a_singularity_falls_back_to_the_position():
    """Next to the wrist singularity (q5 = 0.01 rad) a pose moved 1 mm-mrad along the arm's weakest direction needs a
    joint move far beyond max_joint_change: not reached on the start's branch. The row is commanded for its position
    alone (reached to 1e-9), its status still says the pose is not reached and miss_angle how far the tool stays
    turned."""
    from torchcal.use.compensate import _context, _Goal, rotation_in_base

    model = _with_orientation(calibrated_model(effects=False))
    q0 = poses(model.robot, 4, seed=8)
    q0[:, 4] = 0.01
    with torch.no_grad():
        ctx = _context(model, q0, {})
        p0, R0 = model.probe_in_base(ctx), rotation_in_base(model, ctx)
    _, J, _, _ = _Goal(p0, R0, 0.1).residual(model, ctx)
    weak = torch.linalg.svd(J).U[..., -1]  # (N, 6): the residual direction the arm can barely move along
    eps = 1e-3
    targets, R = p0 + eps * weak[:, :3], tf.so3_exp(eps * weak[:, 3:] / 0.1) @ R0
    res = compensate(model, targets, q0, frame="base", orientations=R)
    assert res.counts()["converged"] == 0 and bool(res.position_only.all())
    assert float(res.miss.max()) <= 1e-9 and float(res.miss_angle.min()) > 1e-4
    assert float((res.q - q0).abs().max()) <= 0.3  # on the start's branch
    with torch.no_grad():
        assert float((model.probe_in_base(Context(q=res.q)) - targets).norm(dim=-1).max()) <= 1e-9


@pytest.mark.parametrize("six_d", [False, True])
def test_jacobian_of_a_few_rows_in_one_pass_equals_one_pass_per_component(monkeypatch, six_d):
    # the solver's residual of a few rows takes its Jacobian from one backward pass over copies of the rows: the
    # residual, the Jacobian and the misses must be those of one pass per component
    from torchcal.use import compensate as comp

    model = _with_orientation(calibrated_model()) if six_d else calibrated_model()
    q = poses(model.robot, 3)
    with torch.no_grad():
        ctx = Context(q=q)
        p = model.probe_in_base(ctx)
        R = comp.rotation_in_base(model, ctx) if six_d else None
    g = torch.Generator().manual_seed(5)
    goal = comp._Goal(p, R)
    near = Context(q=q + 1e-2 * torch.randn(q.shape, generator=g, dtype=F64))
    one = goal.residual(model, near)
    monkeypatch.setattr(comp, "ONE_PASS_ROWS", 0)
    per_component = goal.residual(model, near)
    assert float(per_component[1].abs().max()) > 0.1
    for a, b in zip(one, per_component):
        if a is not None:
            assert torch.allclose(a, b, rtol=1e-12, atol=1e-15)
