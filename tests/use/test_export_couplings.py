"""Found couplings export as readings maps: a DH file holds ``dq_j = c q_k`` in its ``readings:`` block exactly (the
run's own predictions, reloaded as ``--robot``), a URDF and the UR driver's file say they cannot hold it."""

import json

import pytest
import torch

import torchcal
from torchcal.effects import Context, Coupling, Cyclic, MeasurementModel
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.sim.campaign import EffectSpec, SimConfig, simulate
from torchcal.use.export import check_export, export_run, fold_couplings

F64 = torch.float64
FANUC = "tests/robot/data/fanuc_like.yaml"


@pytest.mark.parametrize("robot", ["ur5", FANUC])
def test_folding_couplings_into_the_readings_map_keeps_the_forward_kinematics(robot):
    """Two couplings and a cyclic error: the folded robot with the cyclic error alone predicts what the model does
    (on a robot with a readings map too, whose map the couplings compose with)."""
    r = torchcal.load_robot(robot)
    q = r.limits[:, 0] + (r.limits[:, 1] - r.limits[:, 0]) * torch.rand(
        40, r.dof, generator=torch.Generator().manual_seed(1), dtype=F64
    )
    cyc = Cyclic(2, harmonics=(1,), a=[1e-4], b=[0.0])
    model = MeasurementModel(r, [Coupling(5, 4, c=2e-3), cyc, Coupling(2, 1, c=-7e-4)])
    folded = fold_couplings(model)
    assert [e.kind for e in folded.effects] == ["cyclic"] and folded.robot.has_readings_map
    assert len(model.effects) == 3 and model.robot.has_readings_map == (robot == FANUC)  # the original untouched
    ctx = Context(q=q)
    with torch.no_grad():
        gap = (folded(ctx) - model(ctx)).norm(dim=-1).max()
    assert float(gap) < 1e-12
    A = folded.robot.readings.matrix().detach()
    assert float(A[4, 3] - r.readings.matrix().detach()[4, 3]) != 0.0


@pytest.fixture(scope="module")
def coupled_run(tmp_path_factory):
    """A UR5 campaign with a wrist coupling 5 <- 4 of 2e-3: the default run names it (its only effect)."""
    c = simulate(
        SimConfig(robot="ur5", poses=150, test_poses=40, seed=2, effects=[EffectSpec.parse("coupling:5<-4=2e-3")])
    )
    run = calibrate("ur5", c.train, Options.of(seed=0, holdout=0.25, trajectory=False))
    assert [e.label() for e in run.model.effects] == ["coupling(joint 5 <- 4)"], run.effects_report
    return c, run, write_run(run, tmp_path_factory.mktemp("coupled") / "run")


@pytest.mark.slow
def test_a_dh_export_holds_the_coupling_in_its_readings_block_and_reloads_as_the_full_run(coupled_run, tmp_path):
    c, run, run_dir = coupled_run
    f = tmp_path / "robot.yaml"
    ex = export_run(run_dir, "dh", f)
    assert ex.which == "run" and ex.held == ("coupling(joint 5 <- 4)",) and not ex.left_out
    text = f.read_text()
    assert "readings:" in text and "coupling(joint 5 <- 4) in its readings: block" in text
    report = json.loads((run_dir / "report.json").read_text())
    assert ex.rmse_mm == pytest.approx(report["rmse_after_mm"], rel=1e-9)
    # loaded back as --robot, with the run's instrument pose and lever arm: the run's predictions of the test rows
    loaded = torchcal.load_robot(f)
    assert loaded.has_readings_map
    with torch.no_grad():
        T = loaded(c.test.q)
        mine = run.model.robot
        p_base = (T[:, :3, :3] @ mine.t_flange_probe().unsqueeze(-1)).squeeze(-1) + T[:, :3, 3]
        Ti = mine.T_tracker_base()
        p = (Ti[:3, :3] @ p_base.T).T + Ti[:3, 3]
        want = run.model(Context(q=c.test.q))
    assert float((p - want).norm(dim=-1).max()) < 1e-9
    chk = check_export(run_dir, f)
    assert chk.which == "run" and chk.fk_gap_mm < 1e-9 and chk.rmse_mm == pytest.approx(ex.rmse_mm, rel=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("fmt,suffix", [("urdf", ".urdf"), ("ur-ros2", ".yaml")])
def test_a_format_without_a_readings_map_says_it_cannot_hold_the_coupling(coupled_run, tmp_path, fmt, suffix):
    _, _, run_dir = coupled_run
    f = tmp_path / f"robot{suffix}"
    ex = export_run(run_dir, fmt, f)
    assert ex.which == "standalone" and ex.left_out == ("coupling(joint 5 <- 4)",)
    assert ex.cannot_hold and "cannot hold coupling(joint 5 <- 4)" in ex.summary and "--format dh" in ex.summary
    text = f.read_text()
    assert "cannot hold coupling(joint 5 <- 4)" in text and "NOT in this file: coupling(joint 5 <- 4)" in text
