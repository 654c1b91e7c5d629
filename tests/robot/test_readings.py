"""Joint readings that are not the model's joints (issue 25 item 2): the readings map of a FANUC-style parallelogram
(``tests/robot/data/fanuc_like.yaml``) and of URDF mimic joints (``tests/robot/data/mimic_column.urdf``), its
calibration, and the coupling effect the closed loop names."""

import csv
import dataclasses
import json
from pathlib import Path

import pytest
import torch
import yaml

import torchcal
from torchcal.cli import main
from torchcal.errors import RobotSpecError
from torchcal.pipeline import Options
from torchcal.report.rundir import write_run
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.use.rundir import load_model

DATA = Path(__file__).parent / "data"
FANUC = str(DATA / "fanuc_like.yaml")
MIMIC = str(DATA / "mimic_column.urdf")
F64 = torch.float64


def _plain(tmp_path: Path) -> Path:
    """The FANUC-like table without its readings block: a robot whose files hold the model joints."""
    doc = yaml.safe_load(Path(FANUC).read_text())
    doc.pop("readings")
    path = tmp_path / "fanuc_plain.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_map_is_applied_at_every_entry_point():
    robot, plain = torchcal.load_robot(FANUC), torchcal.load_robot(FANUC)
    A = robot.readings.matrix().detach()
    assert robot.dof == robot.n_joints == 6 and robot.has_readings_map
    g = torch.Generator().manual_seed(0)
    r = torch.rand(7, 6, generator=g, dtype=F64) - 0.5
    q = r @ A.T
    assert torch.equal(q[:, 2], -(r[:, 1] + r[:, 2])) and torch.equal(q[:, 3:], -r[:, 3:])
    # the chain of the same geometry fed the model joints: the plain robot's entry points (no map)
    plain.readings = torchcal.robot.readings.Readings.identity(6)
    torch.testing.assert_close(robot(r), plain(q), rtol=0, atol=1e-15)
    torch.testing.assert_close(robot.probe_in_base(r), plain.probe_in_base(q), rtol=0, atol=1e-15)
    _, J = robot.probe_jacobian(r)
    _, Jq = plain.probe_jacobian(q)
    torch.testing.assert_close(J, Jq @ A, rtol=0, atol=1e-14)
    F, _ = robot.joint_frames(r)
    assert F.shape == (7, 6, 4, 4)


def test_readings_jacobian_agrees_with_differences():
    robot = torchcal.load_robot(FANUC)
    robot.tool.nominal.copy_(torch.tensor([0.01, 0.02, 0.1], dtype=F64))
    q = torch.rand(5, 6, generator=torch.Generator().manual_seed(1), dtype=F64)
    infos = [i for i in robot.parameter_info() if i.group == "readings"]
    assert [i.name for i in infos] == [f"readings.c{a}" for a in ("1_1", "2_2", "3_2", "3_3", "4_4", "5_5", "6_6")]
    assert all(i.unit == "1" for i in infos)
    cols = [("readings", i.index[0] * 6 + i.index[1]) for i in infos]
    _, J = robot.tracker_jacobian(q, cols)
    eps = 1e-6
    for k, info in enumerate(infos):
        d = robot.readings.delta
        with torch.no_grad():
            d[info.index] = eps
            hi = robot.probe_position(q)
            d[info.index] = -eps
            lo = robot.probe_position(q)
            d[info.index] = 0.0
        torch.testing.assert_close(J[..., k], (hi - lo) / (2 * eps), rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    "block, message",
    [
        ("{coupling: [[1, 0], [0, 1]]}", "must have 6 rows"),
        (
            "{coupling: [[1,0,0,0,0,0], [0,1,0,0,0,0], [0,1,0,0,0,0], [0,0,0,1,0,0], [0,0,0,0,1,0], [0,0,0,0,0,0]]}",
            "rank",
        ),
        (
            "{coupling: [[1,0,0,0,0,.nan], [0,1,0,0,0,0], [0,0,1,0,0,0], [0,0,0,1,0,0], [0,0,0,0,1,0], [0,0,0,0,0,1]]}",
            "finite",
        ),
        (
            "{coupling: [[1,0,0,0,0,0], [0,1,0,0,0,0], [0,0,1,0,0,0], [0,0,0,1,0,0], [0,0,0,0,1,0], [0,0,0,0,0,1]], "
            "offset: [0, 0]}",
            "offset",
        ),
        ("{coupling: [[1]], ratio: 2}", "unknown keys"),
    ],
)
def test_bad_readings_block_is_named(tmp_path, block, message):
    doc = Path(FANUC).read_text().split("readings:")[0] + f"readings: {block}\n"
    path = tmp_path / "bad.yaml"
    path.write_text(doc)
    with pytest.raises(RobotSpecError, match=message) as e:
        torchcal.load_robot(path)
    assert str(path) in str(e.value) and "readings" in str(e.value)


def _rmse_mm(run_dir: Path) -> float:
    return json.loads((run_dir / "report.json").read_text())["rmse_after_mm"]


def _write_model_joints(src: Path, dst: Path, A: torch.Tensor) -> None:
    """``src`` with its readings q1..q6 replaced by the model joints ``A q`` (the hand-mapped file)."""
    lines = src.read_text().splitlines()
    head = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    rows = list(csv.reader(lines[head:]))
    cols = [rows[0].index(f"q{k + 1}") for k in range(6)]
    for row in rows[1:]:
        q = torch.tensor([float(row[c]) for c in cols], dtype=F64) @ A.T
        for c, v in zip(cols, q.tolist()):
            row[c] = repr(v)
    dst.write_text("\n".join(lines[:head] + [",".join(r) for r in rows]) + "\n")


@pytest.mark.slow
def test_parallelogram_readings_match_the_hand_mapped_file_through_the_cli(tmp_path):
    """Fed its controller readings with a readings block, the arm reaches the held-out error of the same data mapped to
    model joints by hand and calibrated with the plain table; compensate writes readings that reach the targets."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--robot", FANUC, "--out", str(sim), "--poses", "300", "--test-poses", "60", "--seed",
                 "3", "--quiet"]) == 0  # fmt: skip
    assert main(["calibrate", str(sim / "train.csv"), "--robot", FANUC, "--out", str(tmp_path / "cal"),
                 "--method", "kinematic", "--quiet"]) == 0  # fmt: skip
    A = torchcal.load_robot(FANUC).readings.matrix().detach()
    _write_model_joints(sim / "train.csv", tmp_path / "mapped.csv", A)
    assert main(["calibrate", str(tmp_path / "mapped.csv"), "--robot", str(_plain(tmp_path)), "--out",
                 str(tmp_path / "hand"), "--method", "kinematic", "--quiet"]) == 0  # fmt: skip
    ours, hand = _rmse_mm(tmp_path / "cal"), _rmse_mm(tmp_path / "hand")
    assert abs(ours - hand) <= 0.05 * hand, (ours, hand)
    # compensate: the measured test points as targets, readings out; they are the test file's readings to the
    # model's accuracy (a model joint would differ by J2 + J3 or a sign)
    out = tmp_path / "joints.csv"
    assert main(["compensate", str(tmp_path / "cal"), str(sim / "test.csv"), "--out", str(out), "--quiet"]) == 0
    lines = [line for line in out.read_text().splitlines() if not line.startswith("#")]
    rows = list(csv.DictReader(lines))
    test = torchcal.data.read_measurements(sim / "test.csv", dof=6)
    q_out = torch.tensor([[float(r[f"q{k + 1}"]) for k in range(6)] for r in rows], dtype=F64)
    assert all(r["status"] == "converged" for r in rows)
    model, _ = load_model(tmp_path / "cal")
    with torch.no_grad():
        miss = (model.predict(q_out) - test.p).norm(dim=-1)
    assert float(miss.max()) < 1e-6
    assert float((q_out - test.q).abs().max()) < 5e-3


def test_ratio_error_is_recovered_within_three_sigma():
    campaign = simulate(SimConfig(robot=FANUC, poses=300, test_poses=0, seed=5, ratio_errors={"readings.c3_3": 2e-3}))
    run = torchcal.calibrate(FANUC, campaign.train, Options(method="kinematic"))
    res = run.fits[-1].result
    k = res.names.index("readings.c3_3")
    est, std = float(res.x[k]), float(res.std[k])
    assert abs(est - 2e-3) < 3 * std, (est, std)
    assert std < 5e-4  # determined by the data, not by the 0.1 % prior alone
    assert float(run.model.robot.readings.delta.detach()[2, 2]) == pytest.approx(est)


def test_mimic_urdf_loads_calibrates_and_exports(tmp_path):
    robot = torchcal.load_robot(MIMIC)
    assert (robot.dof, robot.n_joints) == (3, 4)
    assert robot.reading_names == ["pan", "lower", "elbow"]
    r = torch.tensor([[0.1, 0.2, -0.3]], dtype=F64)
    torch.testing.assert_close(robot.model_joints(r), torch.tensor([[0.1, 0.2, 0.25, -0.3]], dtype=F64))
    campaign = simulate(SimConfig(robot=MIMIC, poses=150, test_poses=30, seed=2))
    assert campaign.train.q.shape[1] == 3
    run = torchcal.calibrate(MIMIC, campaign.train, Options(method="kinematic"))
    assert run.stages[-1].rmse < 0.5 * run.stages[0].rmse
    write_run(run, tmp_path / "cal")
    urdf = (tmp_path / "cal" / "robot_calibrated.urdf").read_text()
    assert '<mimic joint="lower"' in urdf
    again = torchcal.load_robot(tmp_path / "cal" / "robot_calibrated.urdf", tip_link="flange")
    assert again.dof == 3
    q = campaign.test.q
    torch.testing.assert_close(again(q), run.model.robot(q).detach(), rtol=0, atol=1e-12)
    p = torchcal.use.rundir.predict(tmp_path / "cal", campaign.test)
    assert float((p - campaign.test.p).norm(dim=-1).max()) < 2e-4


def test_dh_export_writes_model_joints_and_the_map():
    robot = torchcal.load_robot(FANUC)
    text = torchcal.robot.export.urdf_string(robot)
    assert "not the controller's readings" in text and "joint3 = -1.0*J2 + -1.0*J3" in text
    assert "<mimic" not in text  # no model joint follows one reading that another joint follows too


def test_simulated_coupling_is_named_by_the_closed_loop():
    """A wrist coupling the readings block does not declare (J5's error proportional to J4's reading, a
    differential's ratio): the loop names it as a coupling, not as geometry or a learned field."""
    campaign = simulate(
        SimConfig(robot=FANUC, poses=250, test_poses=0, seed=4, effects=[EffectSpec.parse("coupling:5<-4=80um")])
    )
    run = torchcal.calibrate(FANUC, campaign.train, Options())
    found = [(e["kind"], e["joint"]) for e in run.effects_report]
    assert ("coupling", 5) in found, found
    eff = next(e for e in run.model.effects if e.kind == "coupling")
    assert eff.source == 4


@pytest.mark.slow
def test_a_urdf_arm_without_a_readings_map_has_its_coupling_named_and_its_urdf_export_says_it_cannot_hold_it(
    tmp_path,
):
    """The same wrist coupling on a robot described by a URDF (no readings map, no mechanism declared): the default
    method names it, and a URDF export says that the format cannot hold it."""
    from torchcal.report.rundir import write_run
    from torchcal.use.export import export_run

    campaign = simulate(
        SimConfig(robot="ur5.urdf", poses=200, test_poses=0, seed=3, effects=[EffectSpec.parse("coupling:5<-4=2e-3")])
    )
    run = torchcal.calibrate("ur5.urdf", campaign.train, Options())
    assert [e["name"] for e in run.effects_report] == ["coupling:5<-4"], run.effects_report
    eff = next(e for e in run.model.effects if e.kind == "coupling")
    assert eff.source == 4 and float(eff.c.detach()) == pytest.approx(2e-3, rel=0.1)
    ex = export_run(write_run(run, tmp_path / "run"), "urdf", tmp_path / "robot.urdf")
    assert "cannot hold coupling(joint 5 <- 4)" in (tmp_path / "robot.urdf").read_text() and ex.cannot_hold


def test_every_arm_gets_a_coupling_candidate_for_every_pair_of_moving_joints():
    """Couplings are offered on every robot (not only where a readings map declares a mechanism), between every
    ordered pair of joints that move; a joint that does not move drives none."""
    from torchcal.diagnose.candidates import MIN_LEVER, bonferroni_factors, candidates, joint_levers
    from torchcal.effects import Context

    q = torch.rand(20, 6, generator=torch.Generator().manual_seed(0), dtype=F64)
    urdf = str(Path(__file__).resolve().parents[2] / "robots" / "ur5.urdf")
    for robot in (torchcal.load_robot("ur5"), torchcal.load_robot(FANUC), torchcal.load_robot(urdf)):
        cands, _ = candidates(robot, Context(q=q))
        pairs = {(c.joint, c.source) for c in cands if c.kind == "coupling"}
        # a joint that does not move the probe (the last one, with the probe on its axis) shows no error at all
        moving = [j for j in range(1, 7) if float(joint_levers(robot, q)[j - 1]) >= MIN_LEVER]
        assert len(moving) >= 5 and pairs == {(j, k) for j in moving for k in range(1, 7) if j != k}, robot.name
        # the pairs share one member's level: the other candidates keep theirs
        factors = dict(zip((c.name for c in cands), bonferroni_factors(cands)))
        members = len(cands) - len(pairs) + 1
        assert factors["coupling:5<-4"] == members * len(pairs) and factors["cyclic:1"] == members
    q[:, 3] = 0.4  # joint 4 held still: nothing couples to it
    cands, skipped = candidates(torchcal.load_robot("ur5"), Context(q=q))
    assert not [c for c in cands if c.kind == "coupling" and c.source == 4]
    assert {s["name"]: s["reason"] for s in skipped}["coupling:5<-4"] == "joint 4 does not move over the data"


def test_coupling_spec_and_dataclass_round_trip():
    spec = EffectSpec.parse("coupling:3<-2=50um")
    assert (spec.kind, spec.joint, spec.source, spec.size) == ("coupling", 3, 2, 5e-5)
    with pytest.raises(torchcal.errors.OptionError, match="two different joints"):
        EffectSpec.parse("coupling:3<-3")
    assert dataclasses.asdict(spec)["source"] == 2


def test_a_coupling_is_held_to_a_physical_ratio_not_to_the_transmission_error_bound():
    """A coupling is a linear law with one parameter: its ratio is bounded (MAX_COUPLING, 1 %), not its size over
    the source's range, which for a 0.2 % ratio error over a wrist's turns is tens of mrad and real."""
    from torchcal.effects import Coupling
    from torchcal.effects.joint import MAX_COUPLING, MAX_JOINT_ERROR, joint_function_check

    robot = torchcal.load_robot("ur5")
    q = torch.zeros(20, 6, dtype=torch.float64)
    q[:, 1] = torch.linspace(-0.1, 0.1, 20, dtype=torch.float64)  # the source seen over a narrow range only
    lo, hi = (float(v) for v in robot.limits[1])
    real = Coupling(3, 2, c=2e-3)
    assert 2e-3 * (hi - lo) / 2 > 2 * MAX_JOINT_ERROR  # beyond the open forms' bound over the source's range
    assert joint_function_check(real, q, robot) is None
    large = Coupling(3, 2, c=-2 * MAX_COUPLING)
    why = joint_function_check(large, q, robot)
    assert why is not None and "ratio -0.02 rad/rad exceeds the physical bound of 0.01" in why
    assert f"{0.02 * (hi - lo) / 2 * 1e3:.3g} mrad over joint 2's range" in why
    assert joint_function_check(large, q, robot, max_size=None) is None  # no bound asked for


def test_a_small_cross_term_is_a_coupling_and_a_reading_in_encoder_counts_is_refused():
    """A readings map's bound is on each reading's scale (its largest entry): an exported run's folded coupling
    dq_6 = 8e-6 q_5 loads, a reading that moves its joint by 1e-6 rad per unit (encoder counts) does not."""
    from torchcal.robot.readings import check_coupling

    A = torch.eye(6, dtype=torch.float64)
    A[5, 4] = 8.25e-6  # the coupling's cross-term
    assert check_coupling(A.tolist(), 6, "coupling") is None
    B = torch.eye(6, dtype=torch.float64)
    B[2, 2] = 1e-6
    assert "ratio of size 1e-06" in check_coupling(B.tolist(), 6, "coupling")
    B[2, 2] = 1e12
    assert "ratio of size 1e+12" in check_coupling(B.tolist(), 6, "coupling")
