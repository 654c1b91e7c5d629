"""The outside-style trajectory generator: seeded, the field of the size asked, the path inside the joint limits
and through much of them, the continuation after the training part in time."""

import math

import pytest
import torch

from torchcal.effects import Context
from torchcal.errors import OptionError
from torchcal.sim import write_campaign
from torchcal.sim.outside import FIELD_KINDS, OutsideTrajectory, joint_field, simulate_outside_trajectory

pytestmark = pytest.mark.usefixtures("one_thread")


def _spec(**kw):
    return OutsideTrajectory(**{"samples": 1500, "seed": 4, **kw})


def _field(c) -> torch.Tensor:
    """The noiseless tanh field ``(N, 3)`` [m, tracker frame], from the formula and parameters in truth.json."""
    f = c.truth["field"]
    w1, b1, w2 = (torch.tensor(f[k], dtype=torch.float64) for k in ("w1", "b1", "w2"))
    d = f["scale"] * c.truth["spec"]["size"] * torch.tanh(c.q_true @ w1.T + b1) @ w2.T
    return d @ torch.tensor(c.truth["instrument"]["T_tracker_base"], dtype=torch.float64)[:3, :3].T


def test_seeded_and_split_in_time():
    a, b = simulate_outside_trajectory(_spec()), simulate_outside_trajectory(_spec())
    assert torch.equal(a.train.q, b.train.q) and torch.equal(a.test.p, b.test.p)
    other = simulate_outside_trajectory(_spec(seed=5))
    assert not torch.allclose(other.train.q, a.train.q)
    assert (a.train.n, a.test.n) == (1200, 300)  # the first 80 % train
    # the continuation follows the training part: one sampling interval later, one small step away
    t = torch.cat([a.train.t, a.test.t])
    assert torch.allclose(t.diff(), torch.full((len(t) - 1,), 4.0, dtype=torch.float64))
    assert float(a.test.t[0] - a.train.t[-1]) == pytest.approx(4.0)
    step = (a.test.q[0] - a.train.q[-1]).abs().max()
    assert float(step) < 3 * float(a.q_true.diff(dim=0).abs().max())
    assert torch.equal(a.q_true[a.train.n :], a.q_true[-a.test.n :])


def test_path_inside_the_limits_and_through_much_of_them():
    c = simulate_outside_trajectory(OutsideTrajectory(seed=2))  # the full 7342 samples
    q = c.q_true
    assert (q >= -math.pi).all() and (q <= math.pi).all()
    covered = (q.max(0).values - q.min(0).values) / (2 * math.pi)
    assert float(covered.mean()) > 0.3 and float(covered.min()) > 0.15, covered
    # a continuous path: no jumps between samples, and not the same sine on every joint
    assert float(q.diff(dim=0).abs().max()) < 0.02
    periods = c.truth["path"]["periods_samples"]
    assert all(3 <= len(p) <= 5 for p in periods) and len({round(p[0], 6) for p in periods}) == len(periods)


def test_field_of_the_size_asked_and_measured_noise():
    c = simulate_outside_trajectory(_spec(size=1.5e-4, field="tanh", width=16))
    d = _field(c)
    assert float(d.norm(dim=-1).square().mean().sqrt()) == pytest.approx(1.5e-4, rel=1e-9)
    assert c.truth["field"]["width"] == 16 and len(c.truth["field"]["w1"]) == 16
    # the measurements are the true geometry plus this field plus noise: what is left is the noise
    with torch.no_grad():
        p0 = c.model(Context(q=c.q_true))
    left = torch.cat([c.train.p, c.test.p]) - p0 - d
    assert float(left.square().mean().sqrt()) < 2 * 15e-6
    # the measurements differ from the noiseless positions by the field and the noise, nothing else
    none = simulate_outside_trajectory(_spec(field="none"))
    with torch.no_grad():
        p0 = none.model(Context(q=none.q_true[: none.train.n]))
    noise = (none.train.p - p0).norm(dim=-1).square().mean().sqrt()
    assert 15e-6 * math.sqrt(3) * 0.8 < float(noise) < 15e-6 * math.sqrt(3) * 1.5  # tracker noise, joint noise small


@pytest.mark.parametrize("kind", FIELD_KINDS)
def test_every_field_kind_has_unit_rms_and_is_smooth(kind):
    g = torch.Generator().manual_seed(0)
    q = torch.linspace(-2.0, 2.0, 400, dtype=torch.float64)[:, None] * torch.tensor([1.0, -0.5, 0.8, 0.3, -1.0, 0.6])
    d, rec = joint_field(kind, q, 8, 1.5, g)
    assert d.shape == (400, 3) and rec["kind"] == kind
    assert float(d.norm(dim=-1).square().mean().sqrt()) == pytest.approx(1.0, rel=1e-12)
    assert float(d.diff(dim=0).norm(dim=-1).max()) < 0.5  # smooth: small change between neighbouring joints


def test_writes_the_files_and_rejects_bad_specs(tmp_path):
    c = simulate_outside_trajectory(_spec(field="fourier"))
    paths = write_campaign(c, tmp_path)
    assert paths["train"].read_text().count("\n") > c.train.n and paths["truth"].exists()
    with pytest.raises(OptionError, match="field"):
        OutsideTrajectory(field="gp")
    with pytest.raises(OptionError, match="train_fraction"):
        OutsideTrajectory(train_fraction=1.0)
    with pytest.raises(OptionError, match="periods"):
        OutsideTrajectory(periods=(10.0, 5.0))
