"""Validation that sees the edge: an open joint form that wins in the middle of its joint's range and loses at its
edges is rejected with that reason; one that holds at the edges passes."""

import copy
from types import SimpleNamespace

import pytest
import torch

from torchcal.data import Measurements
from torchcal.effects import Cyclic, MeasurementModel, Transmission
from torchcal.estimate.fit import GEOMETRIC_GROUPS, place_instrument_and_tool, solve
from torchcal.pipeline import Options
from torchcal.pipeline.loop import EDGE_SHARE, _edge_split, _validate_edge
from torchcal.robot import load_robot

F64 = torch.float64
pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _campaign(joint_error, n=600, seed=0):
    """UR5 poses whose joint 2 is off by ``joint_error(q2)`` [rad], measured with 10 um noise."""
    g = torch.Generator().manual_seed(seed)
    robot = load_robot("ur5")
    q = (torch.rand(n, 6, generator=g, dtype=F64) - 0.5) * 2.0
    q[:, 1] = -1.6 + 1.2 * (torch.rand(n, generator=g, dtype=F64) - 0.5)
    qt = q.clone()
    qt[:, 1] = qt[:, 1] + joint_error(q[:, 1])
    with torch.no_grad():
        p = robot.probe_in_base(qt) + 1e-5 * torch.randn(n, 3, generator=g, dtype=F64)
    return Measurements(q=q, p=p)


def _check(data, cand_effect):
    opts = Options(seed=0)
    base = MeasurementModel(load_robot("ur5"))
    place_instrument_and_tool(base.robot, data.q, data.p)

    def fit_on(m, d, stage, *, covariance=True):
        return solve(m, d, GEOMETRIC_GROUPS, opts.fit, stage, trajectory=False, effects=True, covariance=covariance)

    fit_on(base, data, "base")
    cand = SimpleNamespace(name=f"{cand_effect.kind}:2", make=lambda: copy.deepcopy(cand_effect))
    trial = copy.deepcopy(base)
    trial.add(cand_effect)
    v = SimpleNamespace(trial=trial, candidate=cand, validation={}, passed=True, reason="")
    _validate_edge(v, base, fit_on, data, trajectory=False, alpha_val=0.05, cache={})
    return v


def test_the_edge_split_holds_out_the_outer_share_on_each_side():
    q = torch.linspace(0, 1, 101, dtype=F64)[:, None].repeat(1, 6)
    mid, edge = _edge_split(q, 3)
    assert len(edge) == 20 and len(mid) == 81 and set(mid.tolist()).isdisjoint(edge.tolist())
    assert float(q[edge, 2].min()) == 0.0 and float(q[mid, 2].min()) >= EDGE_SHARE - 1e-12


def test_a_form_that_wins_in_the_middle_and_loses_at_the_edge_is_rejected():
    # the joint error is a bump in the middle of q2's range and nothing at its edges; a quadratic fitted on the
    # middle bends the wrong way beyond it, so the model with it predicts the edge poses worse than without it
    data = _campaign(lambda q2: 4e-4 * torch.exp(-(((q2 + 1.6) / 0.25) ** 2)))
    v = _check(data, Transmission(2, degree=2))
    assert not v.passed and "wins in the middle and loses at the edge" in v.reason, v.validation
    assert v.validation["edge"]["rmse_with_mm"] > v.validation["edge"]["rmse_without_mm"]


def test_a_form_that_holds_at_the_edges_passes():
    data = _campaign(lambda q2: 3e-4 * torch.sin(2 * q2))
    v = _check(data, Cyclic(2, harmonics=(2,)))
    assert v.passed, v.reason
    assert v.validation["edge"]["rmse_with_mm"] < v.validation["edge"]["rmse_without_mm"]
