"""Robust estimation: gross errors found and left out (linear toy), the robust rigid start, and end to end on a
simulated UR5 campaign with 10 mm shifts, one gross held-out row, and rows in millimetres among rows in metres."""

import json
import math

import pytest
import torch

from experiments.gross_errors import contaminate, gross_error_trial
from torchcal.cli import main
from torchcal.data import read_measurements, write_measurements
from torchcal.estimate.lm import levenberg_marquardt
from torchcal.estimate.rigid import fit_instrument_and_tool, robust_instrument_and_tool
from torchcal.estimate.robust import chi2_isf, chi2_sf, robust_least_squares
from torchcal.pipeline import Options, calibrate
from torchcal.robot import load_robot
from torchcal.robot import transforms as tf
from torchcal.sim import SimConfig, simulate

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def test_chi2_quantiles_match_tables():
    assert chi2_isf(0.05, 3) == pytest.approx(7.814727903, rel=1e-8)
    assert chi2_isf(0.5, 3) == pytest.approx(2.365973884, rel=1e-8)
    assert chi2_isf(1e-3, 1) == pytest.approx(10.82756617, rel=1e-8)
    assert chi2_sf(chi2_isf(1e-6, 3), 3) == pytest.approx(1e-6, rel=1e-6)


def _toy(seed: int, n: int = 60, outliers: dict[int, float] | None = None):
    """A linear toy: n groups of 3 observations of a 4-parameter linear model, unit noise."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(3 * n, 4, generator=g, dtype=F64)
    x_true = torch.tensor([1.0, -2.0, 0.5, 3.0], dtype=F64)
    y = A @ x_true + torch.randn(3 * n, generator=g, dtype=F64)
    for i, size in (outliers or {}).items():
        y[3 * i : 3 * i + 3] += size / math.sqrt(3.0)
    return (lambda x: A @ x - y), x_true


def test_linear_toy_finds_the_gross_errors_and_recovers_the_clean_fit():
    fun, x_true = _toy(1, outliers={7: 400.0, 23: -600.0, 41: 250.0})
    res = robust_least_squares(fun, torch.zeros(4, dtype=F64), 60, gross=0.0)
    assert res.status == "converged"
    assert torch.nonzero(~res.kept).flatten().tolist() == [7, 23, 41]
    assert bool((res.statistic[~res.kept] > res.threshold).all())
    # the same estimate as least squares on the good groups alone
    clean_fun, _ = _toy(1)
    keep = torch.ones(180, dtype=torch.bool)
    keep[21:24] = keep[69:72] = keep[123:126] = False
    A = torch.func.jacfwd(clean_fun)(torch.zeros(4, dtype=F64))[keep]
    b = -clean_fun(torch.zeros(4, dtype=F64))[keep]
    x_ls = torch.linalg.lstsq(A, b.unsqueeze(-1)).solution.squeeze(-1)
    assert torch.allclose(res.result.x, x_ls, atol=1e-8)
    # plain least squares with the gross errors in it is far off
    fun_all = torch.func.jacfwd(fun)(torch.zeros(4, dtype=F64))
    x_bad = torch.linalg.lstsq(fun_all, -fun(torch.zeros(4, dtype=F64)).unsqueeze(-1)).solution.squeeze(-1)
    assert float((x_bad - x_true).norm()) > 5 * float((res.result.x - x_true).norm())


def test_screening_fits_stop_early_but_the_last_is_finished():
    """The reweighting rounds and the deciding snooping fits stop at a loose stat_tol; the fit the result carries is
    the least-squares fit of the kept groups at the caller's tolerance, with the normal matrix of those groups."""
    lin, _ = _toy(2, outliers={5: 500.0, 30: -400.0})

    def fun(x):  # mildly nonlinear, so that the loose and the tight stops fall on different iterations
        return lin(x) + 3.0 * torch.sin(x).repeat(45)

    res = robust_least_squares(fun, torch.zeros(4, dtype=F64), 60, gross=0.0, stat_tol=0.0)
    assert res.status == "converged" and torch.nonzero(~res.kept).flatten().tolist() == [5, 30]
    keep = res.kept.repeat_interleave(3).to(F64)
    ref = levenberg_marquardt(lambda x: fun(x) * keep, torch.zeros(4, dtype=F64))
    assert torch.allclose(res.result.x, ref.x, atol=1e-6)  # the loose fit alone stops 1.8 away
    J = torch.func.jacfwd(fun)(res.result.x)[keep > 0]
    assert torch.allclose(res.result.normal, J.T @ J, rtol=1e-10)


def test_linear_toy_clean_data_rejects_at_most_the_stated_rate():
    # family-wise level 0.1 with the test alone (gross bound off): over 50 clean data sets a data set loses a
    # row in about 5 (at most 10 % by Bonferroni); 14 or more would have probability < 1e-3
    alpha, trials = 0.1, 50
    lost = 0
    for seed in range(trials):
        fun, _ = _toy(100 + seed)
        res = robust_least_squares(fun, torch.zeros(4, dtype=F64), 60, alpha=alpha, gross=0.0)
        lost += res.n_rejected > 0
    assert lost <= 13
    # and at the default level with the gross-error bound, nothing in clean data
    for seed in range(10):
        fun, _ = _toy(300 + seed)
        assert robust_least_squares(fun, torch.zeros(4, dtype=F64), 60).n_rejected == 0


def test_robust_rigid_start_survives_shifts_and_millimetre_rows():
    robot = load_robot("ur5")
    g = torch.Generator().manual_seed(3)
    q = (torch.rand(300, 6, generator=g, dtype=F64) - 0.5) * 4.0
    with torch.no_grad():
        T_fl = robot(q)
    T_true = tf.homogeneous(
        tf.rpy_to_matrix(torch.tensor([0.01, -0.02, 2.0], dtype=F64)), torch.tensor([2.0, -1.0, 0.3], dtype=F64)
    )
    lever = torch.tensor([0.01, -0.02, 0.1], dtype=F64)
    p = tf.transform_points(T_true, T_fl[:, :3, :3] @ lever + T_fl[:, :3, 3])
    p = p + 15e-6 * torch.randn(p.shape, generator=g, dtype=F64)
    T0, t0, _ = fit_instrument_and_tool(T_fl, p)
    bad = p.clone()
    u = torch.randn(15, 3, generator=g, dtype=F64)
    bad[:15] += 0.01 * u / u.norm(dim=-1, keepdim=True)
    bad[100:105] *= 1000.0
    T_ls, _, _ = fit_instrument_and_tool(T_fl, bad)
    assert float((T_ls[:3, 3] - T0[:3, 3]).norm()) > 1.0  # least squares is dragged far away
    T, t, rms, w = robust_instrument_and_tool(T_fl, bad)
    assert float((T[:3, 3] - T0[:3, 3]).norm()) < 1e-5 and float((t - t0).norm()) < 1e-5
    assert bool((w[:15] == 0).all()) and bool((w[100:105] == 0).all())
    assert rms < 5e-5
    T2, t2, _ = fit_instrument_and_tool(T_fl, bad, robust=True)
    assert torch.equal(T2, T) and torch.equal(t2, t)


# ------------------------------------------------------------------------------------------------
# end to end: a simulated UR5 campaign, method kinematic, compared on the campaign's separate clean test file


@pytest.fixture(scope="module")
def campaign_and_clean_run():
    torch.set_num_threads(1)
    c = simulate(SimConfig(robot="ur5", poses=800, test_poses=200, seed=11))
    run = calibrate("ur5", c.train, Options(method="kinematic"))
    return c, run


def _trial(campaign_and_clean_run, **kw):
    c, run = campaign_and_clean_run
    return gross_error_trial(11, campaign=c, clean_run=run, method="kinematic", **kw)


def test_clean_campaign_loses_no_row(campaign_and_clean_run):
    _, run = campaign_and_clean_run
    assert run.screening is not None
    assert run.screening.training.n_rejected == 0 and run.screening.holdout.n_rejected == 0
    assert len(run.train_idx) == 640 and len(run.holdout_idx) == 160


def test_five_percent_of_rows_shifted_by_10mm(campaign_and_clean_run):
    r = _trial(campaign_and_clean_run, mode="shift", fraction=0.05, size=0.01)
    assert r["n_contaminated"] == 40
    assert r["found_rate"] >= 0.9
    assert r["false_rate"] <= 0.01
    assert r["test_ratio"] <= 1.2
    assert r["holdout_rmse_contaminated_mm"] <= 1.2 * r["holdout_rmse_clean_mm"]


def test_one_gross_training_row_does_not_degrade(campaign_and_clean_run):
    r = _trial(campaign_and_clean_run, mode="shift", count=1, size=0.01, where="training")
    assert r["rejected_training_lines"] == r["contaminated_lines"] and r["false_rejections"] == 0
    assert r["test_ratio"] <= 1.02


def test_one_gross_holdout_row_is_named_and_left_out(campaign_and_clean_run):
    r = _trial(campaign_and_clean_run, mode="shift", count=1, size=0.01, where="holdout")
    assert r["rejected_holdout_lines"] == r["contaminated_lines"] and r["rejected_training_lines"] == []
    assert r["holdout_rmse_contaminated_mm"] <= 1.05 * r["holdout_rmse_clean_mm"]
    assert r["test_ratio"] == pytest.approx(1.0, abs=1e-12)  # the training rows are the clean ones


def test_rows_in_millimetres_are_rejected_with_a_hint(campaign_and_clean_run, tmp_path):
    c, clean = campaign_and_clean_run
    rows = torch.tensor([5, 111, 222, 333, 700])
    dirty = contaminate(c.train, rows, mode="mm")
    path = tmp_path / "train.csv"
    write_measurements(path, dirty)
    out = tmp_path / "run"
    assert main(["calibrate", str(path), "--robot", "ur5", "--method", "kinematic", "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    o = report["outliers"]
    named = o["training"]["rows"] + o["holdout"]["rows"]
    lines = read_measurements(path).lines  # the file's own lines (its comment lines count)
    assert sorted(r["line"] for r in named) == [lines[i] for i in rows.tolist()]
    assert all("looks like millimetres" in r["hint"] and r["size_mm"] > 1e5 for r in named)
    assert sorted(o["lines"]) == sorted(r["line"] for r in named)
    assert report["n_train"] + report["n_holdout"] == 795
    # the fit is unharmed: the held-out error as on the clean file
    assert report["rmse_after_mm"] <= 1.05 * clean.stages[-1].rmse * 1e3
    assert "Gross errors left out" in (out / "report.md").read_text()
