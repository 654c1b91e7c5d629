"""Kernel correction: fits local structure, is chosen only when validation data demand it, reloads exactly."""

import os
from pathlib import Path

import pytest
import torch

import torchcal
from torchcal.effects import Context, MeasurementModel
from torchcal.effects.kernel import fit_kernel_correction, paired_improvement
from torchcal.pipeline import Options, calibrate

F64 = torch.float64
IPA = Path(
    os.environ.get(
        "TORCHCAL_IPA_DATA", Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "ur10-ipa"
    )
)


def test_kernel_learns_a_local_field_and_ignores_noise():
    robot = torchcal.load_robot("ur5")
    g = torch.Generator().manual_seed(0)
    q = (torch.rand(900, 6, generator=g, dtype=F64) * 2 - 1) * 1.5
    field = 2e-4 * torch.stack(
        [torch.sin(2 * q[:, 1]) * torch.cos(1.5 * q[:, 2]), torch.cos(2 * q[:, 0]), torch.sin(1.5 * q[:, 3] + q[:, 1])],
        -1,
    )
    noise = 2e-5 * torch.randn(900, 3, generator=g, dtype=F64)
    eff, info = fit_kernel_correction(
        robot, q[:600], (field + noise)[:600], q_val=q[600:750], y_val=(field + noise)[600:750]
    )
    with torch.no_grad():
        pred = eff(robot, Context(q=q[750:]))
    before = float(field[750:].norm(dim=-1).square().mean().sqrt())
    after = float((field[750:] - pred).norm(dim=-1).square().mean().sqrt())
    assert after < 0.35 * before
    # pure noise: the chosen setting predicts next to nothing
    eff0, _ = fit_kernel_correction(robot, q[:600], noise[:600], q_val=q[600:750], y_val=noise[600:750])
    with torch.no_grad():
        assert float(eff0(robot, Context(q=q[750:])).norm(dim=-1).max()) < 2e-5


def test_a_local_search_finds_the_full_grid_s_choice_with_fewer_factorisations():
    """From an earlier fit's setting, from a far one, and (no start, the default) from the best length scale at
    the middle noise ratio."""
    robot = torchcal.load_robot("ur5")
    g = torch.Generator().manual_seed(3)
    q = (torch.rand(500, 6, generator=g, dtype=F64) * 2 - 1) * 1.5
    y = 2e-4 * torch.stack([torch.sin(2 * q[:, 1]), torch.cos(2 * q[:, 0]), torch.sin(q[:, 3])], -1)
    y = y + 2e-5 * torch.randn(500, 3, generator=g, dtype=F64)
    full, info = fit_kernel_correction(robot, q[:350], y[:350], q_val=q[350:], y_val=y[350:], exhaustive=True)
    assert len(info["grid"]) == 30
    for start in ((info["best"]["length_scale_m"], info["best"]["noise_ratio"]), (0.5, 3.0), (0.011, 0.03), None):
        local, linfo = fit_kernel_correction(robot, q[:350], y[:350], q_val=q[350:], y_val=y[350:], start=start)
        assert linfo["best"] == info["best"]
        assert len(linfo["grid"]) < len(info["grid"])
        assert torch.equal(local.alpha, full.alpha) and torch.equal(linfo["val_errors"], info["val_errors"])


def test_paired_improvement():
    g = torch.Generator().manual_seed(1)
    e0 = torch.rand(400, generator=g, dtype=F64)
    assert paired_improvement(e0, 0.8 * e0).p_value < 1e-6
    assert paired_improvement(e0, e0).p_value == pytest.approx(0.5)


@pytest.mark.slow
def test_auto_adds_nothing_to_clean_data_and_a_kernel_reloads_exactly(tmp_path):
    from torchcal.sim import SimConfig, simulate

    c = simulate(SimConfig(robot="ur5", poses=500, test_poses=50, seed=31))
    run = calibrate("ur5", c.train, Options())
    assert run.effects_report == [] and [s.name for s in run.stages] == ["nominal", "geometric"]
    assert run.rejected and run.rejected[0]["kind"] == "learned"
    # a kernel effect saved in a run directory comes back bit for bit
    from torchcal.report.rundir import write_run
    from torchcal.use.rundir import load_model

    kern, _ = fit_kernel_correction(
        run.robot,
        c.train.q[:300],
        1e-4 * torch.sin(c.train.q[:300, :3]),
        q_val=c.train.q[300:],
        y_val=1e-4 * torch.sin(c.train.q[300:, :3]),
    )
    run.model.add(kern)
    write_run(run, tmp_path / "run")
    model, _ = load_model(tmp_path / "run")
    with torch.no_grad():
        assert torch.equal(model(Context(q=c.test.q)), run.model(Context(q=c.test.q)))
    assert isinstance(model, MeasurementModel)


@pytest.mark.slow
@pytest.mark.skipif(not IPA.is_dir(), reason=f"ur10-ipa data not found at {IPA}; set TORCHCAL_IPA_DATA")
def test_real_ur10_series_c_default_method_beats_045mm():
    """The issue's real-data target. The search for named effects (``diagnose``) is switched off here: on
    these 2773 poses it runs about 20 joint refits (minutes on 2 cores) for named effects worth 0.01 mm
    next to the learned model's 0.2 mm, and it is tested on simulated data (tests/diagnose); docs/real-data.md's
    numbers come from the full default run (scripts/ur10_real.py)."""
    from torchcal.data import read_ipa

    m = read_ipa(IPA / "Series_C" / "measurements_random_poses.csv")
    run = calibrate("ur10", m, Options.of(diagnose=False))
    st = {s.name: s.rmse for s in run.stages}
    assert st["geometric"] < 0.55e-3 < st["nominal"]
    assert run.stages[-1].rmse <= 0.45e-3
    assert "learned" in [e["kind"] for e in run.effects_report]
