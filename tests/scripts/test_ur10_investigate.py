"""scripts/ur10_investigate.py (experiments.ur10_investigate): its pair search and correlation helpers
on synthetic data, and a run on the real
UR10 Series D (ISO cubes, 632 poses) when the ur10-ipa data are present."""

import importlib
import math
import os
from pathlib import Path

import pytest
import torch
from _cli import run_script

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "real" / "ur10-ipa"


def load_script():
    """The experiment behind the script (its helpers live in the package)."""
    return importlib.import_module("experiments.ur10_investigate")


# ----------------------------------------------------------------------------- helpers, no data needed


def test_revisit_pairs_match_brute_force():
    mod = load_script()
    g = torch.Generator().manual_seed(1)
    q = (torch.rand(300, 6, generator=g, dtype=torch.float64) - 0.5) * 6
    q[:, 0] = torch.round(q[:, 0] * 20) / 20  # many rows share the first joint: long sorted runs
    q[150:170] = q[:20] + (torch.rand(20, 6, generator=g, dtype=torch.float64) - 0.5) * 1.8e-3  # revisits
    q[170:175] = q[:5] + 3e-3  # too far in every joint
    tol = 1e-3
    brute = {(i, j) for i in range(300) for j in range(i + 1, 300) if bool(((q[i] - q[j]).abs() < tol).all())}
    found = {tuple(p) for p in mod.revisit_pairs(q, tol).tolist()}
    assert found == brute
    assert {(i, 150 + i) for i in range(20)} <= found and not any(b >= 170 for _, b in found)


def test_correlation_curves_see_a_smooth_field_and_skip_revisits():
    mod = load_script()
    g = torch.Generator().manual_seed(2)
    q = (torch.rand(400, 6, generator=g, dtype=torch.float64) - 0.5) * 2
    q[200:] = q[:200] + torch.randn(200, 6, generator=g, dtype=torch.float64) * 0.01  # close partners
    q[380:, :3] = q[100:120, :3]  # ... and 20 with the arm of another row but a wrist of their own
    # a residual field in q1-q3 alone, correlation length 0.2 rad (random Fourier features of a Gaussian kernel)
    w = torch.randn(3, 300, generator=g, dtype=torch.float64) / 0.2
    phase = torch.rand(300, generator=g, dtype=torch.float64) * 2 * math.pi
    r = torch.cos(q[:, :3] @ w + phase) @ torch.randn(300, 3, generator=g, dtype=torch.float64) * 1e-5
    res = mod.correlation_curves(q, q[:, :3], r, 1e-3, torch.tensor([[0, 200]]))
    joint = {b["hi"]: b for b in res["joint"]}
    assert joint[0.05]["corr"] > 0.95  # near partners share the residual
    assert all(abs(b["corr"]) < 0.1 for b in res["joint"] if b["lo"] >= 1.6)  # far apart they do not
    wrist = [b for b in res["wrist_at_same_arm"] if b["lo"] >= 0.4 and b["n_pairs"]]
    assert sum(b["n_pairs"] for b in wrist) >= 15 and all(b["corr"] > 0.9 for b in wrist)  # the wrist plays no part
    assert sum(b["n_pairs"] for b in res["joint"]) == 400 * 399 // 2 - 1  # one pair declared a revisit
    assert res["half_corr_rad"] is not None and 0.05 < res["half_corr_rad"] < 1.0


def test_half_distance_interpolates_in_log_distance():
    mod = load_script()
    curve = [
        {"lo": 0.01, "hi": 0.04, "n_pairs": 100, "corr": 0.9},
        {"lo": 0.04, "hi": 0.16, "n_pairs": 100, "corr": 0.1},
    ]
    # centres 0.02 and 0.08; 0.5 lies halfway, so at their geometric mean
    assert mod.half_distance(curve) == pytest.approx(0.04)
    assert mod.half_distance([{"lo": 0.01, "hi": 0.04, "n_pairs": 100, "corr": 0.9}]) is None


# ----------------------------------------------------------------------------- Series D


@pytest.fixture(scope="module")
def series_d():
    data = Path(os.environ.get("TORCHCAL_IPA_DATA", DEFAULT_DATA))
    if not (data / "Series_D").is_dir():
        pytest.skip(f"ur10-ipa data (Series_D) not found at {data}; set TORCHCAL_IPA_DATA")
    res, stderr = run_script("ur10_investigate.py", str(data), "--series", "D", "--json", "--threads", "1", timeout=240)
    assert "=== Series D" in stderr
    (s,) = res["series"]
    return s


def test_series_d_json_has_the_four_parts(series_d):
    s = series_d
    for key in (
        "rms_mm",
        "rms_nominal_mm",
        "pairs",
        "covariates",
        "joint_regression",
        "drift",
        "correlation",
        "components_rms_mm",
        "large_residual_lines",
    ):
        assert key in s
    assert set(s["pairs"]) == {"revisit", "other_orientation", "other_ik_branch"}
    assert {"reach_m", "tracker_distance_m", "view_angle_rad", "tool_tilt_rad", "temperature_c", "row"} <= set(
        s["covariates"]
    )
    assert s["n"] == 632 and s["n_fit"] == 631  # all rows but the one calibrate() keeps out


def test_series_d_geometric_fit_halves_the_error(series_d):
    # measured 0.405 mm after the kinematic fit vs 0.807 mm with the nominal geometry
    assert 0.3 < series_d["rms_mm"] < 0.55
    assert series_d["rms_mm"] < 0.6 * series_d["rms_nominal_mm"]


def test_series_d_repeatability_is_far_below_the_residual(series_d):
    rev = series_d["pairs"]["revisit"]
    # the ISO cycles revisit 31 poses (86 pairs); measured 0.032 mm per pose vs 0.405 mm RMS, corr 0.99
    assert rev["n_pairs"] == 86
    assert math.isfinite(rev["per_pose_mm"]) and 0 < rev["per_pose_mm"] < 0.25 * series_d["rms_mm"]
    assert rev["corr"] > 0.9
    assert rev["n_outliers"] == 0
    assert series_d["pairs"]["other_ik_branch"]["n_pairs"] == 0  # D has no second IK branch


def test_series_d_residual_grows_with_reach(series_d):
    reach = series_d["covariates"]["reach_m"]
    # measured slope 0.31 mm/m, t 8.9; RMS 0.33 mm in the shortest fifth, 0.51 mm in the longest
    assert reach["slope"] > 0 and reach["t"] > 3
    assert reach["bins"][-1]["rms_mm"] > 1.2 * reach["bins"][0]["rms_mm"]


def test_series_d_correlation_is_local_in_joint_space(series_d):
    c = series_d["correlation"]
    joint = [b for b in c["joint"] if b["n_pairs"] >= 20]
    # measured 0.95 below 0.02 rad, about 0 beyond 0.8 rad; half-correlation at 0.13 rad
    assert joint[0]["hi"] <= 0.05 and joint[0]["corr"] > 0.8
    assert all(abs(b["corr"]) < 0.15 for b in joint if b["lo"] >= 0.8)
    assert 0.05 < c["half_corr_rad"] < 0.4
