"""torchcal.stats: the one seeded split (with revisit groups), the paired tests, the chi-square helpers."""

import math

import pytest
import torch

from torchcal import stats as S

F64 = torch.float64


def _old_split(n, k, seed):  # the held-out split as calibrate.py wrote it before the split was shared
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    return torch.sort(perm[k:]).values, torch.sort(perm[:k]).values


def test_split_without_revisits_is_the_plain_seeded_permutation():
    q = torch.rand(300, 6, dtype=F64, generator=torch.Generator().manual_seed(1)) * 4 - 2
    for seed in (0, 3):
        s = S.split(300, 60, seed=seed, q=q)
        old_keep, old_held = _old_split(300, 60, seed)
        assert torch.equal(s.keep, old_keep) and torch.equal(s.held, old_held)
        assert s.merged_groups == 0 and s.merged_rows == 0
    # unsorted, from a generator that goes on: the permutation's order, and the generator advanced past it
    g = torch.Generator().manual_seed(5)
    keep, held = S.split(300, 60, generator=g, q=q, sort=False)
    perm = torch.randperm(300, generator=torch.Generator().manual_seed(5))
    assert torch.equal(held, perm[:60]) and torch.equal(keep, perm[60:])


def test_revisits_go_wholly_to_one_side_and_are_counted():
    gen = torch.Generator().manual_seed(2)
    q = torch.rand(200, 6, dtype=F64, generator=gen) * 4 - 2
    # 40 configurations measured again (within 0.2 mrad), one of them three times
    again = q[:40] + 2e-4 * (torch.rand(40, 6, dtype=F64, generator=gen) - 0.5)
    q = torch.cat([q, again, q[:1] + 1e-4])
    labels = S.revisit_groups(q)
    assert int(labels.max()) + 1 == 200
    s = S.split(len(q), 48, seed=0, q=q)
    assert s.merged_groups == 40 and s.merged_rows == 81
    held = set(s.held.tolist())
    assert len(held) >= 48 and len(held) + len(s.keep) == len(q)
    for g in range(200):
        rows = set(torch.nonzero(labels == g).flatten().tolist())
        assert rows <= held or not (rows & held), f"group {g} split across the sides"
    # a tolerance below the revisits' scatter sees no revisit: the plain split
    assert S.split(len(q), 48, seed=0, q=q, group_tol=1e-6).merged_groups == 0


def test_revisit_groups_are_transitive_and_numbered_by_first_row():
    q = torch.tensor([[0.0, 0.0], [5.0, 5.0], [0.0008, 0.0], [0.0016, 0.0], [5.0, 5.0005]], dtype=F64)
    assert S.revisit_groups(q).tolist() == [0, 1, 0, 0, 1]
    assert S.revisit_groups(q, tol=0.0).tolist() == [0, 1, 2, 3, 4]


def test_last_rows_for_trajectories():
    keep, held = S.split(10, 3, last=True)
    assert keep.tolist() == list(range(7)) and held.tolist() == [7, 8, 9]


def test_holdout_count_rules():
    assert S.holdout_count(160, 0.2) == 32 and S.holdout_count(7, 0.2) == 1
    assert S.holdout_count(14, 0.2, minimum=3) == 3 and S.holdout_count(19, 0.2) == 4
    # every validation split: a fifth rounded to the nearest, at least three
    assert S.validation_count(160) == 32 and S.validation_count(19) == 4 and S.validation_count(7) == 3


def test_paired_tests():
    e0 = torch.rand(400, dtype=F64, generator=torch.Generator().manual_seed(0)) + 0.5
    assert S.paired_improvement(e0, 0.8 * e0).p_value < 1e-6
    assert S.paired_improvement(e0, e0).p_value == pytest.approx(0.5)
    smooth = torch.sin(torch.linspace(0, 6, 400, dtype=F64)) * 0.01
    plain = S.paired_test(e0, e0 * 0.999 + smooth, ordered=False)
    ordered = S.paired_test(e0, e0 * 0.999 + smooth, ordered=True)
    assert ordered.lag1_autocorrelation > 0.5 and abs(ordered.z) < abs(plain.z)
    assert S.rmse(torch.tensor([3.0, 4.0], dtype=F64)) == pytest.approx(math.sqrt(12.5))
    assert math.isnan(S.rmse(torch.zeros(0, dtype=F64)))


def test_chi2_helpers_are_exact():
    # textbook values: chi2_{0.95, 1} = 3.841459, chi2_{0.95, 10} = 18.307038
    assert S.chi2_quantile(0.95, 1) == pytest.approx(3.841458820694124, rel=1e-12)
    assert S.chi2_quantile(0.95, 10) == pytest.approx(18.307038053275146, rel=1e-12)
    p, l10 = S.chi2_sf_log10(3.841458820694124, 1)
    assert p == pytest.approx(0.05, rel=1e-12) and l10 == pytest.approx(math.log10(0.05), rel=1e-12)
    p, l10 = S.chi2_sf_log10(2000.0, 2)  # far in the tail: p underflows, its log does not
    assert p == 0.0 and l10 == pytest.approx(-1000.0 / math.log(10.0), rel=1e-9)
    assert math.isnan(S.chi2_quantile(0.5, 0))


def test_fit_statuses_name_the_solvers_statuses():
    from torchcal.estimate.fit import FitStatus
    from torchcal.estimate.lm import STATUSES

    assert {s.value for s in FitStatus} == set(STATUSES)
    assert "diverged" in (FitStatus.DIVERGED,) and f"{FitStatus.CONVERGED}" == "converged"


@pytest.mark.slow
def test_a_calibration_keeps_revisited_configurations_on_one_side():
    from torchcal._threads import torch_threads
    from torchcal.data import Measurements
    from torchcal.pipeline import Options, calibrate
    from torchcal.report.rundir import build_report
    from torchcal.sim import SimConfig, simulate

    with torch_threads(1):
        c = simulate(SimConfig(robot="ur5", poses=150, test_poses=10, seed=4))
        m = c.train
        # every third pose measured again (same joints, the second reading 0.1 mrad off, a new position reading)
        again = torch.arange(0, m.n, 3)
        data = Measurements(q=torch.cat([m.q, m.q[again] + 1e-4]), p=torch.cat([m.p, m.p[again] + 1e-5]))
        run = calibrate("ur5", data, Options(method="kinematic", seed=0))
    assert run.split.merged_groups == len(again) and run.split.merged_rows == 2 * len(again)
    labels = S.revisit_groups(data.q)
    assert not set(labels[run.train_idx].tolist()) & set(labels[run.holdout_idx].tolist())
    assert build_report(run)["split"]["merged_groups"] == len(again)
    assert any("revisited joint configurations" in n for n in run.notes)


def test_chi2_tail_agrees_with_scipy_for_integer_and_fractional_dof():
    """The tail is computed in torch (no scipy import on the score tests' path) and agrees with scipy's."""
    from scipy.stats import chi2

    for k in (1, 2, 4, 1.43, 2.29, 7.5, 30):
        for x in (0.0, 0.3, 1.0, 3.8, 12.0, 60.0, 400.0):
            p, _ = S.chi2_sf_log10(x, k)
            assert p == pytest.approx(float(chi2.sf(x, k)), rel=1e-11, abs=1e-300)
