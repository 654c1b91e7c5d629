"""experiments/compensation.py's 6-D summary: the cut against position-only, and the bound the true model sets."""

import math

import torch

from experiments.compensation import POSITION_ROW, SIX_D_ROW, TRUE_MODEL_ROW, six_d_summary

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
