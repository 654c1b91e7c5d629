"""The numpy reference of the kinematic calibration (experiments.numpy_reference, timed by
scripts/bench_kinematic.py): its forward kinematics equal torchcal's, it recovers a noise-free campaign, and its
process imports numpy but not torch."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from experiments import numpy_reference as ref
from torchcal.robot import load_robot


def _ur10_table() -> np.ndarray:
    return np.concatenate([load_robot("ur10").geometry.nominal[:, :4].numpy(), np.zeros((6, 1))], axis=1)


def test_forward_kinematics_equal_torchcals_with_every_dh_element_moved():
    robot = load_robot("ur10")
    rng = np.random.default_rng(3)
    delta = rng.normal(scale=1e-2, size=(6, 5)) * robot.geometry.mask.numpy()  # beta where torchcal frees it
    with torch.no_grad():
        robot.geometry.delta.copy_(torch.from_numpy(delta))
    q = rng.uniform(-3.0, 3.0, size=(50, 6))
    T_ref = ref.forward(_ur10_table() + delta, q)
    with torch.no_grad():
        T_tc = robot(torch.from_numpy(q)).numpy()
    assert np.abs(T_ref - T_tc).max() < 1e-12


def test_a_noise_free_campaign_is_recovered():
    rng = np.random.default_rng(7)
    dh = _ur10_table()
    true = dh.copy()
    true[:, :4] += rng.normal(scale=2e-4, size=(6, 4))
    true[1:3, 4] = rng.normal(scale=2e-4, size=2)  # beta2, beta3: the parallel axes
    q = rng.uniform(-3.0, 3.0, size=(400, 6))
    T_tracker_base = np.eye(4)
    T_tracker_base[:3, :3], T_tracker_base[:3, 3] = ref.so3_exp(np.array([0.1, -0.2, 2.5])), [0.5, -3.5, -1.2]
    T = ref.forward(true, q)
    p_base = T[:, :3, :3] @ np.array([1e-3, -2e-3, 0.093]) + T[:, :3, 3]
    p = p_base @ T_tracker_base[:3, :3].T + T_tracker_base[:3, 3]
    out = ref.calibrate(dh[:, :4], q, p, np.arange(320), np.arange(320, 400))
    assert out["status"] == "converged"
    assert out["rmse_start_holdout_mm"] > 0.1  # the nominal model misses by far more than the fit leaves
    assert out["rmse_holdout_mm"] < 1e-6 and out["rmse_train_mm"] < 1e-6


def test_the_reference_process_imports_numpy_and_not_torch():
    folder = str(Path(ref.__file__).parent)
    code = f"import sys; sys.path.insert(0, {folder!r}); import numpy_reference; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert json.loads(out.strip().lower()) is False


@pytest.mark.slow
def test_the_bench_fits_both_on_calibrates_rows_and_times_both_commands(tmp_path):
    from experiments.bench_kinematic import commands, write_problem

    rng = np.random.default_rng(11)
    true = _ur10_table()
    true[:, :4] += rng.normal(scale=2e-4, size=(6, 4))
    q = rng.uniform(-3.0, 3.0, size=(150, 6))
    T = ref.forward(true, q)
    p = T[:, :3, :3] @ np.array([0.0, 0.0, 0.093]) + T[:, :3, 3] + rng.normal(scale=1e-5, size=(150, 3))
    data = tmp_path / "campaign.csv"
    rows = [",".join(f"{v:.12g}" for v in row) for row in np.concatenate([q, p], axis=1)]
    data.write_text("\n".join(["q1,q2,q3,q4,q5,q6,x,y,z", *rows]) + "\n")
    problem = write_problem(str(data), "ur10", tmp_path / "problem.json")
    assert sorted(problem["train"] + problem["holdout"]) == list(range(150)) and len(problem["holdout"]) == 30
    res = commands(str(data), "ur10", tmp_path / "problem.json", tmp_path, repeats=1)
    assert res["reference"]["status"] == "converged"
    tc, rf = res["rmse_holdout_mm"]["torchcal"], res["rmse_holdout_mm"]["reference"]
    assert 0.01 < rf < 0.05 and abs(tc - rf) < 0.1 * rf  # the noise (10 um per axis, 0.017 mm in 3-D), both
    assert all(res["best"][k]["cpu_s"] > 0 for k in ("torchcal", "reference"))
