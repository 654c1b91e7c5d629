"""One learned correction per station and probe (:class:`~torchcal.effects.grouped.GroupedCorrection`): the dispatch,
the model.json round trip, and the learned stage's grouped candidate on two groups whose residual fields differ."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from torchcal import stats as S
from torchcal.data import Measurements
from torchcal.effects import Context, CorrectionNet, LearnedEffect, MeasurementModel, effect_from_config
from torchcal.effects.grouped import GroupedCorrection
from torchcal.pipeline import Options
from torchcal.pipeline.learned import _grouped_candidate, _groups, _learned_split
from torchcal.robot import load_robot

F64 = torch.float64


def _net(seed: int) -> LearnedEffect:
    return LearnedEffect(CorrectionNet(6, 5, seed=seed))


def test_rows_take_their_groups_correction_and_round_trip():
    eff = GroupedCorrection([(0, 0), (1, 1)], [_net(1), _net(2)])
    g = torch.Generator().manual_seed(0)
    q = torch.rand(9, 6, generator=g, dtype=F64)
    st, pr = torch.tensor([0, 1, 1] * 3), torch.tensor([0, 1, 0] * 3)
    ctx = Context(q=q, station=st, probe=pr)
    with torch.no_grad():
        out = eff(None, ctx)
        assert torch.equal(out[0::3], eff.inner[0].net(q[0::3]))
        assert torch.equal(out[1::3], eff.inner[1].net(q[1::3]))
        assert torch.equal(out[2::3], torch.zeros(3, 3, dtype=F64))  # station 1, probe 0: no correction
        twin = effect_from_config({"class": "GroupedCorrection", **eff.config()})
        twin.load_state_dict(eff.state_dict())
        assert torch.equal(twin(None, ctx), out)
        assert torch.equal(eff(None, ctx), out)  # the cached split gives the same
    assert twin.kind == "learned" and twin.acts_on == "cartesian"


def _campaign(n: int = 400):
    """Two groups (station 0 / probe 0, station 1 / probe 1) whose residual fields differ in sign and shape."""
    g = torch.Generator().manual_seed(5)
    q = (torch.rand(n, 6, generator=g, dtype=F64) * 2 - 1) * 1.5
    grp = (torch.arange(n) % 2).long()
    f0 = torch.stack([torch.sin(2 * q[:, 1]), torch.cos(q[:, 2]), q[:, 0] * 0], 1)
    f1 = torch.stack([-torch.sin(2 * q[:, 1]), torch.sin(q[:, 3]), torch.cos(2 * q[:, 0])], 1)
    corr = 2e-4 * torch.where(grp[:, None] == 0, f0, f1) + 1e-6 * torch.randn(n, 3, generator=g, dtype=F64)
    train = Measurements(
        q=q,
        p=torch.zeros(n, 3, dtype=F64),
        station=grp,
        station_names=("S0", "S1"),
        probe=grp,
        probe_names=("P0", "P1"),
    )
    return train, corr


def test_grouped_candidate_beats_the_shared_one_where_the_fields_differ():
    from torchcal.effects.gp import GPSettings, fit_gp_correction

    train, corr = _campaign()
    opts = Options.of(method="auto", seed=0)
    work = SimpleNamespace(model=MeasurementModel(load_robot("ur5")), options=opts, note=lambda text: None)
    fi, va = _learned_split(train, opts.seed, opts.split.group_tol)
    eff, e_grouped, params = _grouped_candidate(work, train, corr, fi, va)
    assert isinstance(eff, GroupedCorrection) and [g["model"] is not None for g in params["groups"]] == [True, True]
    shared, info = fit_gp_correction(
        Context(q=train.q[fi]), corr[fi], GPSettings(seed=0), ctx_val=Context(q=train.q[va]), y_val=corr[va]
    )
    assert S.rmse(e_grouped) < 0.5 * S.rmse(info["val_errors"])
    ctx = Context.from_measurements(train.subset(va))
    with torch.no_grad():
        assert torch.allclose((corr[va] - eff(None, ctx)).norm(dim=-1), e_grouped, atol=1e-9)


def test_one_group_has_no_grouped_candidate():
    train, corr = _campaign(60)
    one = Measurements(q=train.q, p=train.p)
    assert _groups(one) is None
    opts = Options.of(method="auto", seed=0)
    work = SimpleNamespace(model=MeasurementModel(load_robot("ur5")), options=opts, note=lambda text: None)
    fi, va = _learned_split(one, opts.seed, opts.split.group_tol)
    assert _grouped_candidate(work, one, corr, fi, va) is None


def test_one_station_and_probe_keeps_that_pairs_correction():
    """compensate's single-frame model (:func:`~torchcal.use.rundir.at_station`) carries the picked pair's
    correction, and none where the pair has none, not the first group's."""
    from torchcal.use.rundir import at_station

    robot = load_robot("ur5")
    robot.set_stations(["S0", "S1"])
    robot.set_probes(["P0", "P1"])
    eff = GroupedCorrection([(0, 0), (1, 1)], [_net(1), _net(2)])
    model = MeasurementModel(robot, [eff])
    one, s, p = at_station(model, "S1", "P1")
    assert (s, p) == (1, 1) and one.effects[0] is not eff and isinstance(one.effects[0], LearnedEffect)
    q = torch.rand(4, 6, dtype=F64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert torch.equal(one.effects[0].net(q), eff.inner[1].net(q))
    none, _, _ = at_station(model, "S1", "P0")
    assert len(none.effects) == 0


def test_each_row_has_its_own_groups_predictive_sigma():
    from torchcal.effects.gp import GPSettings, fit_gp_correction
    from torchcal.estimate.covariance import learned_std

    train, corr = _campaign(120)
    gps = []
    for g in (0, 1):
        rows = torch.nonzero(train.station == g).flatten()
        gp, _ = fit_gp_correction(Context(q=train.q[rows]), corr[rows], GPSettings(seed=0))
        gps.append(gp)
    robot = load_robot("ur5")
    eff = GroupedCorrection([(0, 0), (1, 1)], gps)
    q = torch.rand(6, 6, dtype=F64, generator=torch.Generator().manual_seed(2)) * 3 - 1.5
    st, pr = torch.tensor([0, 1, 1, 0, 1, 0]), torch.tensor([0, 1, 0, 0, 1, 1])
    ctx = Context(q=q, station=st, probe=pr)
    out = learned_std(MeasurementModel(robot, [eff]), ctx)
    for g, rows in ((0, [0, 3]), (1, [1, 4])):
        alone = learned_std(MeasurementModel(robot, [gps[g]]), Context(q=q[rows]))
        assert torch.allclose(out[rows], alone, rtol=1e-12, atol=0)
    assert torch.equal(out[[2, 5]], torch.zeros(2, 3, dtype=F64))  # pairs without a correction


def test_a_groups_correction_fades_beyond_the_joints_it_was_measured_over():
    eff = GroupedCorrection([(0, 0)], [_net(1)], regions=[torch.tensor([[-0.5] * 6, [0.5] * 6], dtype=F64)])
    q = torch.zeros(3, 6, dtype=F64)
    q[1, 2] = 0.5  # at the edge: in
    q[2, 2] = 0.5 + 1.0  # a radian beyond q3's range
    ctx = Context(q=q, station=torch.zeros(3, dtype=torch.long), probe=torch.zeros(3, dtype=torch.long))
    with torch.no_grad():
        out, raw = eff(None, ctx), eff.inner[0].net(q)
        assert torch.equal(out[:2], raw[:2])
        assert float(out[2].norm()) < 0.01 * float(raw[2].norm())
        twin = effect_from_config({"class": "GroupedCorrection", **eff.config()})
        twin.load_state_dict(eff.state_dict())
        assert torch.equal(twin(None, ctx), out)
