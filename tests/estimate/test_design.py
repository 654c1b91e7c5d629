"""Greedy D-optimal pose selection (torchcal.estimate.design): the rank-one updates agree with the direct criterion,
the design beats random candidates on it, and it is fast enough for 100 of 10,000 candidates."""

import pytest
import torch

from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.estimate.design import (
    covariance,
    design_problem,
    greedy_d_optimal,
    greedy_design,
    information,
    log_det,
    mean_variance,
)
from torchcal.robot import load_robot
from torchcal.sim.poses import sample_joints


@pytest.fixture(scope="module")
def problem():
    model = MeasurementModel(load_robot("ur5"))
    q = sample_joints(model.robot, 2000, torch.Generator().manual_seed(0))
    return design_problem(model, q)


def test_identifiable_parameters_only(problem):
    # the UR5's dependent parameters are held (identifiability.py: d1, theta1, d3, d4, ... go to the instrument)
    held = {f["name"] for f in problem.identifiability.fixed}
    assert {"d1", "theta1"} <= held
    assert not held & set(problem.names)
    assert problem.A.shape == (2000, 3, len(problem.names))
    # a full-rank information matrix over the candidates: every kept parameter is determined
    assert torch.linalg.matrix_rank(information(problem, torch.arange(2000))) == len(problem.names)


def test_rank_one_updates_agree_with_the_direct_criterion(problem):
    d = greedy_d_optimal(problem, 40, checkpoints=(10, 40))
    assert len(set(d.order.tolist())) == 40
    for k in (10, 40):
        direct = log_det(problem, d.order[:k])
        assert abs(float(d.log_det[k - 1]) - direct) < 1e-8 * abs(direct)
        torch.testing.assert_close(d.information[k], information(problem, d.order[:k]), rtol=1e-10, atol=0)
    assert bool((d.log_det.diff() > 0).all())  # every pose adds information


def test_greedy_beats_random_on_log_det(problem):
    k = 30
    planned = float(greedy_d_optimal(problem, k).log_det[-1])
    random = [
        log_det(problem, torch.randperm(problem.n, generator=torch.Generator().manual_seed(s))[:k]) for s in range(20)
    ]
    assert planned > max(random)
    # and the parameters' volume shrinks with it: the mean log sigma is smaller than the best random design's
    P = len(problem.names)
    assert (planned - max(random)) / (2 * P) > 0.05  # geometric-mean sigma at least 5 % smaller


def test_i_optimal_beats_random_on_the_mean_variance(problem):
    k = 30
    i_opt = greedy_design(problem, k, criterion="I", checkpoints=(k,))
    torch.testing.assert_close(i_opt.information[k], information(problem, i_opt.order), rtol=1e-10, atol=0)
    planned = mean_variance(problem, i_opt.order)
    gen = torch.Generator().manual_seed(0)
    random = [mean_variance(problem, torch.randperm(problem.n, generator=gen)[:k]) for _ in range(20)]
    assert planned < min(random)
    # greedy is no optimum: the D design's mean variance may come out near it, on either side (here within 1 %)
    assert planned < 1.01 * mean_variance(problem, greedy_d_optimal(problem, k).order)
    with pytest.raises(OptionError, match="unknown design criterion"):
        greedy_design(problem, k, criterion="A")


def test_edge_picks_come_from_the_restricted_set(problem):
    restrict = torch.zeros(problem.n, dtype=torch.bool)
    restrict[:50] = True
    d = greedy_d_optimal(problem, 30, restrict=restrict, every=5)
    assert all(int(i) < 50 for i in d.order[4::5])


def test_bad_sizes_are_refused(problem):
    with pytest.raises(OptionError, match="1 to 2000"):
        greedy_d_optimal(problem, 2001)


def test_covariance_inverts_the_information(problem):
    M = information(problem, torch.arange(100))
    torch.testing.assert_close(covariance(M, 2.0) @ M, 2.0 * torch.eye(len(M), dtype=M.dtype), rtol=0, atol=1e-8)


def test_100_of_10000_candidates_distinct_and_gaining():
    """The planning scale of the command (its speed is measured by scripts/bench_plan.py, not here): 100 distinct
    picks of 10,000 candidates, each one adding information."""
    model = MeasurementModel(load_robot("ur5"))
    q = sample_joints(model.robot, 10_000, torch.Generator().manual_seed(1))
    design = greedy_d_optimal(design_problem(model, q), 100)
    assert len(design.order) == 100 and len(set(design.order.tolist())) == 100
    assert bool((design.log_det[1:] > design.log_det[:-1]).all())
