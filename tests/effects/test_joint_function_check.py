"""A fitted joint-angle function must be determined by the poses it was fitted on (never worse than without it)."""

import math

import pytest
import torch

from torchcal.effects import Compliance, Cyclic, Transmission, joint_function_check

F64 = torch.float64


def _poses(lo: float, hi: float, n: int = 200, dof: int = 6, joint: int = 2) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    q = torch.rand(n, dof, generator=g, dtype=F64) * 2.0 - 1.0
    q[:, joint - 1] = lo + (hi - lo) * torch.rand(n, generator=g, dtype=F64)
    return q


def test_a_harmonic_seen_over_its_period_passes():
    q = _poses(-math.pi, math.pi)
    eff = Cyclic(2, harmonics=(4,), a=[2e-4], b=[-1e-4])
    assert joint_function_check(eff, q) is None


def test_a_harmonic_seen_over_a_narrow_range_passes_when_its_terms_add_up():
    q = _poses(0.4, 0.9)
    eff = Cyclic(2, harmonics=(1, 2), a=[3e-4, 1e-4], b=[0.0, 5e-5])
    assert joint_function_check(eff, q) is None


def test_cancelling_terms_are_refused():
    # harmonics 1..6 with 40 rad amplitudes that sum to about 1e-4 rad on a 0.3 rad range: the fit of a real
    # learning-curve subset looked like this and gave 560 mm just beyond its poses
    q = _poses(0.5, 0.8)
    orders = (1, 2, 3, 4, 5, 6)
    qj = q[:, 1]
    X = torch.cat(
        [
            torch.sin(qj[:, None] * torch.tensor(orders, dtype=F64)),
            torch.cos(qj[:, None] * torch.tensor(orders, dtype=F64)),
        ],
        dim=1,
    )
    target = 1e-4 * torch.sin(7.0 * qj)
    big = torch.full((12,), 40.0, dtype=F64)
    # a coefficient vector of size 40 whose function on the poses is the small target (least-norm correction)
    coef = big + torch.linalg.lstsq(X, (target - X @ big)[:, None]).solution[:, 0]
    eff = Cyclic(2, harmonics=orders, a=coef[:6], b=coef[6:])
    why = joint_function_check(eff, q)
    assert why is not None and "cancel" in why


def test_other_kinds_and_polynomials():
    q = _poses(-1.0, 1.0)
    assert joint_function_check(Compliance(2, k=1e-6), q) is None
    assert joint_function_check(Transmission(2, degree=3, c=[1e-4, -5e-5, 2e-5]), q) is None
    # a quadratic and a linear term that cancel over a narrow range far from zero
    q = _poses(1.0, 1.05)
    assert "cancel" in joint_function_check(Transmission(2, degree=2, c=[-1.025e-2, 1e-2]), q)


# ------------------------------------------------------------------ a physical bound on the whole joint range


def _robot():
    import torchcal

    return torchcal.load_robot("ur10")


def test_a_first_harmonic_of_45_mrad_is_refused_over_the_joint_range():
    # a real Series C fit of cyclic(joint 2) (harmonics 1, 2; a first harmonic of 45 mrad that the joint offset
    # cancels over the 1.1 rad of q2 seen): it put the home pose 6 mm off, 0.6 rad beyond the fitted range
    q = _poses(-3.25, -2.13)
    eff = Cyclic(2, harmonics=(1, 2), a=[-0.021, -0.0102], b=[-0.0404, -0.0074])
    assert joint_function_check(eff, q) is None  # terms do not cancel: only the bound finds it
    why = joint_function_check(eff, q, _robot())
    assert why is not None and "exceeds the physical bound of 5 mrad" in why and "-6.283 to 6.283" in why
    assert joint_function_check(eff, q, _robot(), max_size=0.05) is None  # settable


def test_a_small_harmonic_and_a_ratio_error_pass_the_bound():
    q = _poses(-1.0, 1.0)
    robot = _robot()
    assert joint_function_check(Cyclic(4, harmonics=(2,), a=[2.2e-4], b=[1e-4]), q, robot) is None
    assert joint_function_check(Transmission(3, degree=1, c=[1.9e-4]), q, robot) is None  # 1.2 mrad over +-2 pi
    # a ratio error of 2e-3: 12.6 mrad at a full turn, beyond the bound however small it is on the poses
    assert "exceeds" in joint_function_check(Transmission(3, degree=1, c=[2e-3]), q, robot)


def test_the_bound_is_the_same_displacement_at_the_probe_on_a_short_lever():
    # joint 6 turns the probe about its own axis: a lever of centimetres, where an error of tens of micrometres at
    # the probe is several mrad of angle (an outside campaign's harmonic on joint 6). The bound widens to the same
    # displacement as 5 mrad at 1 m, at most tenfold
    from torchcal.effects.joint import MAX_BOUND_SCALE, joint_bound_scale

    q = _poses(-math.pi, math.pi, joint=6)
    robot = _robot()
    assert joint_bound_scale(robot, q, 2) == 1.0  # the shoulder: a lever of a metre or more
    assert joint_bound_scale(robot, q, 6) == MAX_BOUND_SCALE
    assert joint_function_check(Cyclic(6, harmonics=(3,), a=[0.012], b=[0.0]), q, robot) is None
    why = joint_function_check(Cyclic(6, harmonics=(3,), a=[0.06], b=[0.0]), q, robot)
    assert why is not None and "exceeds the physical bound of 50 mrad" in why and "scaled" in why
    assert "exceeds" in joint_function_check(Cyclic(2, harmonics=(3,), a=[0.012], b=[0.0]), _poses(-3.2, 3.2), robot)


def test_physical_forms_are_judged_on_the_poses():
    q = _poses(-1.0, 1.0)
    robot = _robot()
    assert joint_function_check(Compliance(2, k=1e-6), q, robot) is None
    assert "on the fitting poses" in joint_function_check(Compliance(2, k=1e-3), q, robot)  # 1e-3 rad/Nm: absurd


# --------------------------------------------------------------------- open forms fade beyond their region


def test_an_open_form_is_unchanged_on_its_region_and_fades_beyond_it():
    from torchcal.effects import Context
    from torchcal.effects.joint import FADE_LENGTH

    q = _poses(0.4, 0.9)
    eff = Cyclic(2, harmonics=(1, 2), a=[3e-4, 1e-4], b=[2e-4, 5e-5])
    free = eff(None, Context(q=q))[:, 1]
    eff.set_region(q)
    torch.testing.assert_close(eff(None, Context(q=q))[:, 1], free, rtol=0, atol=0)
    hi = float(eff.region[1])
    out = q[:3].clone()
    out[:, 1] = torch.tensor([hi + 0.05, hi + FADE_LENGTH, hi + 0.6], dtype=F64)
    edge = eff.function(torch.tensor([hi], dtype=F64))
    got = eff(None, Context(q=out))[:, 1].detach()
    w = torch.exp(-0.5 * ((out[:, 1] - hi) / FADE_LENGTH) ** 2)
    torch.testing.assert_close(got, edge * w)
    assert abs(float(got[0])) > 0.95 * abs(float(edge))  # just beyond the fitted poses a real effect still holds
    assert abs(float(got[2])) < 0.02 * abs(float(edge))  # 3 fade lengths out: geometry


def test_a_harmonic_sum_seen_over_a_whole_period_does_not_fade():
    from torchcal.effects import Context

    q = _poses(-3.2, 3.2)
    eff = Cyclic(2, harmonics=(2, 4), a=[3e-4, 1e-4], b=[2e-4, 5e-5], region=(-1.6, 1.6))  # period pi
    far = q[:2].clone()
    far[:, 1] = torch.tensor([3.0, -3.0], dtype=F64)
    torch.testing.assert_close(eff(None, Context(q=far))[:, 1], eff.function(far[:, 1]))


def test_the_region_survives_config_and_state_dict():
    from torchcal.effects import effect_from_config

    eff = Transmission(3, degree=2, c=[1e-4, 2e-5], region=(-0.5, 1.25))
    twin = effect_from_config({"class": "Transmission", **eff.config()})
    twin.load_state_dict(eff.state_dict())
    assert twin.region.tolist() == [-0.5, 1.25] and twin.c.tolist() == eff.c.tolist()
    assert "region" in eff.config() and "support" not in eff.config()  # the new name is written
    old = Transmission(3, degree=2)  # a run written before the fade: no region in its config or state dict
    assert "region" not in old.config() and "region" not in old.state_dict()


def test_a_run_written_when_the_region_was_called_support_or_span_still_loads():
    """model.json and model.pt of runs written before "region" was the one word: an open form's ``support`` and a
    drift's ``span``, in the config and in the state dict, load as the region; both names at once are refused."""
    from torchcal.effects import Drift, effect_from_config

    form = Transmission(3, degree=2, c=[1e-4, 2e-5], region=(-0.5, 1.25))
    cfg = {"class": "Transmission", "joint": 3, "degree": 2, "support": [-0.5, 1.25]}  # as an older run wrote it
    state = {("support" if k == "region" else k): v for k, v in form.state_dict().items()}
    assert "support" in state and "region" not in state
    twin = effect_from_config(cfg)
    twin.load_state_dict(state)  # strict: the old key is read, nothing is left over
    assert twin.region.tolist() == [-0.5, 1.25] and twin.c.tolist() == form.c.tolist()
    assert twin.config() == form.config()
    drift = Drift("t", "instrument", rates=[1e-7, 0, 0, 0, 0, 2e-9], region=(0.0, 100.0))
    cfg = {"class": "Drift", "variable": "t", "target": "instrument", "span": [0.0, 100.0]}
    state = {("span" if k == "region" else k): v for k, v in drift.state_dict().items()}
    old = effect_from_config(cfg)
    old.load_state_dict(state)
    assert old.region.tolist() == [0.0, 100.0] and old.rates.tolist() == drift.rates.tolist()
    with pytest.raises(ValueError, match="both 'span' and its newer name 'region'"):
        effect_from_config({**cfg, "region": [0.0, 100.0]})


# ----------------------------------------------------------------------------- a drift in time holds beyond its region


def test_a_drift_in_time_holds_its_value_beyond_the_time_region_it_was_fitted_on():
    from torchcal.effects import Context, Drift, effect_from_config

    eff = Drift("t", "instrument", rates=[1e-7, 0, 0, 0, 0, 2e-9])
    t = torch.linspace(0.0, 100.0, 11, dtype=F64)
    q = torch.zeros(11, 6, dtype=F64)
    free = eff(None, Context(q=q, t=t)).detach()
    eff.set_region(t)
    torch.testing.assert_close(eff(None, Context(q=q, t=t)), free, rtol=0, atol=0)  # unchanged on its region
    later = eff(None, Context(q=q[:2], t=torch.tensor([150.0, 1e6], dtype=F64))).detach()
    torch.testing.assert_close(later, free[-1:].expand(2, 6))  # held at its end value, however far on
    twin = effect_from_config({"class": "Drift", **eff.config()})
    twin.load_state_dict(eff.state_dict())
    assert twin.region.tolist() == [0.0, 100.0]
    warm = Drift("temperature", "scale", rates=[1e-5])
    warm.set_region(t)  # thermal expansion has a law: no region
    assert warm.region is None and "region" not in warm.config()
