"""Simulator: reproducibility, truth, noise levels, line of sight, effect sizes, trajectories."""

import json
import math

import pytest
import torch

import torchcal
from torchcal.effects import Context
from torchcal.errors import OptionError
from torchcal.robot import transforms as tf
from torchcal.sim import EffectSpec, SightRule, SimConfig, simulate, visible, write_campaign

F64 = torch.float64


@pytest.fixture(scope="module")
def campaign():
    return simulate(
        SimConfig(
            robot="ur5",
            poses=300,
            test_poses=100,
            seed=3,
            effects=[EffectSpec.parse("compliance:2=40um"), EffectSpec.parse("cyclic:4=20um")],
        )
    )


def test_same_seed_same_files_other_seed_other_files(tmp_path):
    cfg = dict(robot="ur5", poses=50, test_poses=10, effects=[EffectSpec.parse("backlash:3")])
    a = write_campaign(simulate(SimConfig(seed=7, **cfg)), tmp_path / "a")
    b = write_campaign(simulate(SimConfig(seed=7, **cfg)), tmp_path / "b")
    c = write_campaign(simulate(SimConfig(seed=8, **cfg)), tmp_path / "c")
    for key in ("train", "test", "truth"):
        assert a[key].read_bytes() == b[key].read_bytes(), key
    assert a["train"].read_bytes() != c["train"].read_bytes()


def test_files_follow_the_contract(campaign, tmp_path):
    paths = write_campaign(campaign, tmp_path)
    robot = torchcal.load_robot("ur5")
    m = torchcal.read_measurements(paths["train"], dof=6, joint_limits=robot.limits)
    assert m.n == 300 and m.p is not None and m.t is not None and m.sigma is not None
    assert torch.equal(m.q, campaign.train.q) and torch.equal(m.p, campaign.train.p)
    truth = json.loads(paths["truth"].read_text())
    for key in ("geometry", "instrument", "tool", "noise", "effects", "config", "line_of_sight"):
        assert key in truth
    assert [e["kind"] for e in truth["effects"]] == ["compliance", "cyclic"]


def test_truth_reproduces_the_measurements_within_noise(campaign):
    # the true model at the true joints leaves exactly the tracker noise
    ctx = Context(
        q=campaign.q_true,
        t=torch.cat([campaign.train.t, campaign.test.t]),
        temperature=torch.cat([campaign.train.temperature, campaign.test.temperature]),
    )
    with torch.no_grad():
        p = campaign.model(ctx)
    meas = torch.cat([campaign.train.p, campaign.test.p])
    per_axis = (meas - p).std()
    assert abs(float(per_axis) / 15e-6 - 1.0) < 0.1
    # the truth file alone rebuilds the same geometry, instrument pose and lever arm
    truth = campaign.truth
    robot = torchcal.load_robot("ur5")
    with torch.no_grad():
        robot.geometry.delta.copy_(torch.tensor(truth["geometry"]["delta"], dtype=F64).reshape(6, 5))
        robot.instrument.set_matrix(torch.tensor(truth["instrument"]["T_tracker_base"], dtype=F64))
        robot.tool.nominal.copy_(torch.tensor(truth["tool"]["t_flange_probe"], dtype=F64))
        geo_only = robot.probe_position(campaign.q_true)
        ref = torchcal.MeasurementModel(campaign.model.robot, [])(Context(q=campaign.q_true))
    assert (geo_only - ref).abs().max() < 1e-12


def test_joint_noise_moves_the_probe_by_about_15um():
    # the paper (Sec. 3.1): 0.0005 deg joint noise ~ 1.5e-5 m at the probe
    c = simulate(SimConfig(robot="ur5", poses=400, test_poses=0, seed=4, sigma_tracker=0.0))
    with torch.no_grad():
        p_read = torchcal.MeasurementModel(c.model.robot, [])(Context(q=c.train.q))
    rms = float((p_read - c.train.p).norm(dim=-1).square().mean().sqrt())
    assert 0.7e-5 < rms < 2.5e-5


def test_effect_sizes_are_rms_displacements(campaign):
    for e, want in zip(campaign.truth["effects"], (40e-6, 20e-6)):
        assert abs(e["rms_m"] / want - 1.0) < 1e-6


def test_poses_satisfy_the_line_of_sight_rule(campaign):
    robot = torchcal.load_robot("ur5")
    tracker = torch.tensor(campaign.truth["instrument"]["tracker_in_base_m"], dtype=F64)
    lever = torch.tensor(campaign.truth["tool"]["nominal_lever_arm"], dtype=F64)
    assert visible(robot, campaign.q_true, tracker, lever).all()


def test_line_of_sight_rule_rejects_hidden_and_averted_probes():
    robot = torchcal.load_robot("ur5")
    lever = torch.tensor([0.0, 0.0, 0.1], dtype=F64)
    q = torch.tensor([[0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0]], dtype=F64)  # arm straight up
    with torch.no_grad():
        T = robot(q)[0]
    probe = tf.transform_points(T, lever)
    out = T[:3, :3] @ lever / 0.1
    facing = probe + 2.0 * out
    assert visible(robot, q, facing, lever).item()
    assert not visible(robot, q, probe - 2.0 * out, lever).item()  # reflector turned away
    # with any incidence allowed, a tracker straight behind the flange still cannot see
    # through the wrist: only the occlusion test can reject this one
    rule = SightRule(max_incidence_deg=180.0)
    assert not visible(robot, q, probe - 2.0 * out, lever, rule).item()
    assert visible(robot, q, facing, lever, rule).item()


def test_trajectory_is_continuous_and_split_as_the_paper():
    c = simulate(
        SimConfig(
            robot="ur5",
            trajectory=True,
            samples=1500,
            train_samples=1200,
            seed=5,
            effects=[EffectSpec.parse("backlash:2")],
        )
    )
    assert c.train.n == 1200 and c.test.n == 300
    steps = (c.q_true[1:] - c.q_true[:-1]).abs().max()
    assert float(steps) < 0.02  # rad per sample
    t = torch.cat([c.train.t, c.test.t])
    assert (torch.diff(t) > 0).all()


def test_urdf_robot_and_7_dof(tmp_path):
    c = simulate(
        SimConfig(robot="panda.urdf", poses=60, test_poses=10, seed=6, effects=[EffectSpec.parse("compliance:4")])
    )
    assert c.train.q.shape == (60, 7)


def test_effect_spec_parsing():
    assert EffectSpec.parse("compliance:2=50um") == EffectSpec("compliance", 2, None, 50e-6)
    assert EffectSpec.parse("field=0.6mm").size == pytest.approx(0.6e-3)
    assert EffectSpec.parse("drift:temperature").variable == "temperature"
    for bad, msg in [
        ("compliance", "needs a joint"),
        ("wobble:2", "not one of"),
        ("compliance:2=5", "unit"),
        ("drift:humidity", "drift variable"),
        ("field:3", "takes no joint"),
    ]:
        with pytest.raises(OptionError, match=msg):
            EffectSpec.parse(bad)
    with pytest.raises(OptionError, match="joint 7 is outside 1..6"):
        simulate(SimConfig(robot="ur5", poses=5, effects=[EffectSpec.parse("cyclic:7")]))


def test_a_coupling_given_by_its_ratio_is_simulated_with_that_ratio():
    """``coupling:J<-K=C`` (or ``C rad/rad``) puts ``dq_J = C q_K`` into the truth; truth.json gives the ratio and the
    RMS displacement it made, and moving the source joint alone moves the probe as joint J turned by ``C dq_K``."""
    spec = EffectSpec.parse("coupling:5<-4=-1.5e-3")
    assert (spec.joint, spec.source, spec.ratio, spec.size) == (5, 4, -1.5e-3, None)
    assert EffectSpec.parse("coupling:5<-4=1e-3rad/rad").ratio == 1e-3
    for bad, msg in [
        ("coupling:5<-4=0", "other than 0"),
        ("cyclic:2=1e-3rad/rad", "only a coupling takes a ratio"),
        ("compliance:2=5", "unit"),
    ]:
        with pytest.raises(OptionError, match=msg):
            EffectSpec.parse(bad)
    c = simulate(SimConfig(robot="ur5", poses=30, test_poses=0, seed=3, effects=[spec]))
    (truth,) = c.truth["effects"]
    assert truth["params"] == {"source": 4, "c": pytest.approx(-1.5e-3, rel=1e-12)}
    assert truth["size_m"] == pytest.approx(truth["rms_m"]) and truth["size_m"] > 1e-5
    q = c.train.q[:2].clone()
    q[1, 3] += 0.3  # joint 4 turns by 0.3 rad
    with torch.no_grad():
        moved = c.model(Context(q=q))
        geometric = c.model.robot.probe_position(q)
        q_true = q.clone()
        q_true[:, 4] += -1.5e-3 * q[:, 3]
        expected = c.model.robot.probe_position(q_true)
    assert torch.allclose(moved, expected, atol=1e-12) and not torch.allclose(moved, geometric, atol=1e-6)


@pytest.mark.parametrize("kind", ["multisine", "randomwalk", "sweeps"])
def test_trajectory_families_are_visible_continuous_paths_within_limits(kind):
    """Each family is a sampled path (mostly small steps; a gap only where the line of sight breaks), every
    sample visible and within the limits, and the same seed gives the same path."""
    from torchcal.pipeline import is_trajectory

    cfg = SimConfig(robot="ur5", trajectory=True, path=kind, samples=1500, train_samples=1200, seed=3)
    c = simulate(cfg)
    q = c.q_true
    assert q.shape == (1500, 6)
    steps = torch.diff(q, dim=0).abs().max(dim=-1).values
    assert float(steps.median()) < 0.02
    assert float((steps > 0.05).double().mean()) < 0.02  # gaps are rare
    lo, hi = c.model.robot.limits[:, 0], c.model.robot.limits[:, 1]
    assert bool(((q >= lo) & (q <= hi)).all())
    tracker = torch.tensor(c.truth["instrument"]["tracker_in_base_m"], dtype=torch.float64)
    lever = torch.tensor(cfg.lever_arm, dtype=torch.float64)
    assert bool(visible(c.model.robot, q, tracker, lever).all())
    assert is_trajectory(c.train)
    assert torch.equal(simulate(cfg).q_true, q)


def test_families_differ_in_how_they_revisit():
    """Sweeps repeat one cycle (the continuation revisits the training path); a multi-sine does not."""

    def nearest_gap(kind):
        c = simulate(SimConfig(robot="ur5", trajectory=True, path=kind, samples=2000, train_samples=1600, seed=4))
        tr, te = c.q_true[:1600], c.q_true[1600:]
        return float(torch.cdist(te, tr).min(dim=1).values.median())

    assert nearest_gap("sweeps") < 1e-9
    assert nearest_gap("multisine") > 1e-3
    with pytest.raises(OptionError, match="multisine"):
        SimConfig(trajectory=True, path="zigzag")


def test_a_fixed_tool_axis_takes_several_stations_each_axis_facing_its_instrument_but_one_probe():
    c = simulate(SimConfig(robot="ur5", poses=24, test_poses=8, seed=3, stations=2, tool_axis_deg=0.03))
    assert c.turned is not None and c.turned.n == 8 and c.turned.station_names == ("S1", "S2")
    spread = c.truth["tool_axis"]
    assert spread["max_deg_train_test"] <= 0.03 and spread["min_deg_turned"] >= 30
    a1, a2 = (torch.tensor(spread["per_station"][s]["axis_in_base"]) for s in ("S1", "S2"))
    assert float(a1 @ a2) < 0.999  # each placement's own axis
    with pytest.raises(OptionError, match="a fixed tool axis takes one probe"):
        SimConfig(stations=2, probes=2, tool_axis_deg=0.03)
