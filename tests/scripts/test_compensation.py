"""experiments/compensation.py's 6-D summary: the cut against position-only, and the bound the true model sets."""

import copy
import math

import torch

from experiments.compensation import POSITION_ROW, SIX_D_ROW, TRUE_MODEL_ROW, six_d_summary, true_pose_nearby
from torchcal.effects.base import Context
from torchcal.effects.model import MeasurementModel
from torchcal.robot import load_robot
from torchcal.robot import transforms as tf

F64 = torch.float64


def _entry(rmse_mm: float, turns: torch.Tensor) -> dict:
    return {"rmse_mm": rmse_mm, "orientation": {"rms_deg": math.degrees(float(turns.square().mean().sqrt()))}}


def test_six_d_summary_bounds_the_cut_by_the_true_model_known_answers():
    """Four targets: three whose full pose the true robot reaches (the full model leaves 1 mrad there, position-only
    10 mrad) and one next to a singularity that no model reaches (both leave 30 mrad; the true model 20 mrad). The cut
    over all targets is sqrt(1200 / 903) (the unreached target dominates it), the true model's sqrt(1200 / 400), and on
    the reached targets alone 10."""
    pos = torch.tensor([0.010, 0.010, 0.010, 0.030], dtype=F64)
    six = torch.tensor([0.001, 0.001, 0.001, 0.030], dtype=F64)
    true = torch.tensor([0.0, 0.0, 0.0, 0.020], dtype=F64)
    reached = torch.tensor([True, True, True, False])
    rows = {POSITION_ROW: _entry(0.010, pos), SIX_D_ROW: _entry(0.0105, six), TRUE_MODEL_ROW: _entry(0.0, true)}
    per_target = {
        POSITION_ROW: {"turns": pos, "reached": None},
        SIX_D_ROW: {"turns": six, "reached": torch.tensor([True, True, True, False])},
        TRUE_MODEL_ROW: {"turns": true, "reached": reached},
    }
    out = six_d_summary(rows, per_target)
    assert math.isclose(out["position_ratio"], 1.05, rel_tol=1e-12)
    assert math.isclose(out["orientation_cut"], math.sqrt(1200 / 903), rel_tol=1e-12)
    assert math.isclose(out["true_model_cut"], math.sqrt(1200 / 400), rel_tol=1e-12)
    assert out["true_model_reaches"] == 3
    assert math.isclose(out["cut_where_true_model_reaches"], 10.0, rel_tol=1e-12)


def test_six_d_summary_without_a_reached_target_says_none():
    turns = torch.tensor([0.01, 0.02], dtype=F64)
    rows = {name: _entry(0.01, turns) for name in (POSITION_ROW, SIX_D_ROW, TRUE_MODEL_ROW)}
    per_target = {name: {"turns": turns, "reached": torch.tensor([False, False])} for name in rows}
    out = six_d_summary(rows, per_target)
    assert out["true_model_reaches"] == 0 and out["cut_where_true_model_reaches"] is None
    assert math.isclose(out["true_model_cut"], 1.0, rel_tol=1e-12)


def test_true_pose_nearby_tells_a_pose_out_of_reach_from_a_stalled_solve():
    """The nominal UR5's poses at a stretched elbow (q3 = 0.01 rad: its wrist 10 um short of full reach) lie out of the
    reach of an arm whose upper arm is 0.5 mm shorter: no start within 0.3 rad finds one (eight starts a row here). The
    same arm reaches the nominal poses of a bent elbow (q3 = 0.8 rad) with a small move, and they are found."""
    nominal = load_robot("ur5")
    g = torch.Generator().manual_seed(3)
    nominal.enable_orientation(tf.so3_exp(torch.randn(3, generator=g, dtype=F64)))
    short = copy.deepcopy(nominal)
    with torch.no_grad():
        short.geometry.delta[1, 0] = -0.0005 * math.copysign(1.0, float(short.geometry.nominal[1, 0]))
    q = (torch.rand(6, 6, generator=g, dtype=F64) * 2 - 1) * 2.5
    q[:, 4] = torch.sign(q[:, 4]) * (0.5 + q[:, 4].abs() * 0.4)  # away from the wrist singularity
    q[:3, 2], q[3:, 2] = 0.01, 0.8
    plain = MeasurementModel(nominal, [])
    with torch.no_grad():
        targets, R = plain(Context(q=q)), plain.orientation(Context(q=q))
    truth = MeasurementModel(short, [])
    assert true_pose_nearby(truth, targets, R, q, torch.arange(3), False, starts=8) == 0
    assert true_pose_nearby(truth, targets, R, q, torch.arange(3, 6), False, starts=8) == 3
