"""RegionGate: a learned correction fades back to geometry where it has seen no data."""

import math

import pytest
import torch

from torchcal.effects import Context, CorrectionNet, LearnedEffect, MeasurementModel
from torchcal.effects.region import RegionGate, choose_gate_length
from torchcal.robot import load_robot

F64 = torch.float64


def _net(seed=0):
    net = CorrectionNet(6, 29)
    net.reset_parameters(torch.Generator().manual_seed(seed), gain=2.0)
    return LearnedEffect(net)


def test_gate_is_one_on_the_region_and_fades_away_from_it():
    g = torch.Generator().manual_seed(1)
    region = torch.rand(500, 6, generator=g, dtype=F64) * 0.4  # a small box of joint space
    gate = RegionGate(_net(), region, length=0.1)
    assert torch.allclose(gate.gate(region[::10]), torch.ones(50, dtype=F64))
    far = region[:5] + 3.0
    assert float(gate.gate(far).max()) < 1e-6
    robot = load_robot("ur5")
    ctx = Context(q=far)
    with torch.no_grad():
        assert float(gate(robot, ctx).abs().max()) < 1e-12
    ctx_in = Context(q=region[:7])
    assert torch.allclose(gate(robot, ctx_in), gate.inner(robot, ctx_in))


def test_infinite_length_is_no_gate_and_a_state_dict_round_trip_rebuilds_it():
    region = torch.rand(100, 6, generator=torch.Generator().manual_seed(2), dtype=F64)
    q = region + 2.0
    robot = load_robot("ur5")
    open_gate = RegionGate(_net(), region)
    assert torch.equal(open_gate(robot, Context(q=q)), open_gate.inner(robot, Context(q=q)))
    gate = RegionGate(_net(), region, length=0.3)
    cfg = gate.config()
    assert cfg["inner"]["class"] == "LearnedEffect" and cfg["n_region"] == 100
    rebuilt = RegionGate(
        LearnedEffect(CorrectionNet(6, 29)),
        torch.zeros(cfg["n_region"], cfg["dof"], dtype=F64),
        cfg["length"],
        max_points=cfg["n_region"],
    )
    rebuilt.load_state_dict(gate.state_dict())
    assert torch.equal(rebuilt(robot, Context(q=q[:9])), gate(robot, Context(q=q[:9])))


def test_thinning_keeps_at_most_max_points():
    region = torch.rand(10_000, 6, dtype=F64)
    assert len(RegionGate(_net(), region, max_points=3000).region) <= 3000


def test_a_gate_saved_as_a_support_gate_loads_as_a_region_gate():
    """model.json and model.pt of a run written when the gate was ``SupportGate`` with ``n_support`` points in a
    ``support`` buffer: rebuilt as a RegionGate that predicts the same; written again under the new names."""
    from torchcal.effects import effect_from_config

    gate = RegionGate(_net(), torch.rand(40, 6, generator=torch.Generator().manual_seed(3), dtype=F64), length=0.3)
    cfg = {("n_support" if k == "n_region" else k): v for k, v in gate.config().items()}
    state = {("support" if k == "region" else k): v for k, v in gate.state_dict().items()}
    assert "n_support" in cfg and "support" in state and "region" not in state  # as the older run wrote them
    old = effect_from_config({"class": "SupportGate", **cfg})
    old.load_state_dict(state)  # strict: the old buffer name is read, nothing is left over
    assert isinstance(old, RegionGate) and torch.equal(old.region, gate.region)
    q = torch.rand(9, 6, generator=torch.Generator().manual_seed(4), dtype=F64) + 0.5
    robot = load_robot("ur5")
    with torch.no_grad():
        assert torch.equal(old(robot, Context(q=q)), gate(robot, Context(q=q)))
    assert old.config() == gate.config() and "n_region" in old.config()


def test_refuses_effects_that_do_not_act_on_the_position():
    from torchcal.effects import Compliance

    with pytest.raises(ValueError, match="position correction"):
        RegionGate(Compliance(2, k=1e-6), torch.zeros(3, 6, dtype=F64))


def test_validation_chooses_a_gate_only_where_it_helps():
    """Truth: a field that exists only near the training box. A network that extrapolates a made-up correction
    away from it is beaten by the gated one on the continuation; where the correction holds everywhere, no gate."""
    robot = load_robot("ur5")
    g = torch.Generator().manual_seed(3)
    train_q = torch.rand(400, 6, generator=g, dtype=F64) * 0.3
    valid_q = 0.6 + torch.rand(200, 6, generator=g, dtype=F64) * 0.3  # the path went on elsewhere
    inner = _net(4)
    model_of = lambda eff: MeasurementModel(robot, [eff])  # noqa: E731
    geometric = MeasurementModel(robot, [])

    def score_against(truth):
        def score(gate):
            with torch.no_grad():
                e = model_of(gate)(Context(q=valid_q)) - truth
            return float(e.norm(dim=-1).square().mean().sqrt())

        return score

    with torch.no_grad():
        truth_none = geometric(Context(q=valid_q))  # no field out there
        truth_all = model_of(inner)(Context(q=valid_q))  # the network is right everywhere
    length, table = choose_gate_length(lambda ell: RegionGate(inner, train_q, ell), score_against(truth_none))
    assert math.isfinite(length) and len(table) >= 3
    length, _ = choose_gate_length(lambda ell: RegionGate(inner, train_q, ell), score_against(truth_all))
    assert math.isinf(length)


def test_with_a_fallback_the_whole_prediction_fades_to_the_fallback_geometry_and_reloads():
    """Away from the region, model(q) -> the fallback robot's prediction (tracker frame); on it, the model's own."""
    import copy

    from torchcal.effects import effect_from_config

    own = load_robot("ur5")
    fallback = load_robot("ur5")
    with torch.no_grad():
        own.geometry.delta.add_(1e-4 * own.geometry.mask)  # the filter's own geometry differs from the kinematic one
        fallback.instrument.delta.add_(
            torch.tensor([1e-3, 0, 0, 0, 0, 0], dtype=F64).reshape(fallback.instrument.delta.shape)
        )
    region = torch.rand(300, 6, generator=torch.Generator().manual_seed(5), dtype=F64) * 0.4
    gate = RegionGate(_net(6), region, length=0.1, fallback=copy.deepcopy(fallback))
    model = MeasurementModel(own, [gate])
    far, near = Context(q=region[:4] + 2.5), Context(q=region[:4])
    with torch.no_grad():
        assert torch.allclose(model(far), MeasurementModel(fallback, [])(far), atol=1e-12)
        assert torch.allclose(model(near), MeasurementModel(own, [gate.inner])(near), atol=1e-12)
        cfg = {"class": "RegionGate", **gate.config()}
        rebuilt = MeasurementModel(load_robot("ur5"), [effect_from_config(cfg, load_robot("ur5"))])
        rebuilt.load_state_dict(model.state_dict())
        assert torch.equal(rebuilt(far), model(far)) and torch.equal(rebuilt(near), model(near))
