"""``torchcal plan`` (torchcal.use.plan): the command end to end into a calibration, and the predicted held-out
error against the measured one on a simulated campaign."""

import json

import pytest
import torch

from experiments.plan_poses import Protocol, compare
from torchcal.cli import main
from torchcal.data import Measurements, read_measurements, write_measurements
from torchcal.effects import Context
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.robot import load_robot
from torchcal.sim import SimConfig, simulate
from torchcal.sim.poses import sample_joints
from torchcal.use.plan import PlanOptions, plan_poses


@pytest.fixture(scope="module")
def campaign():
    return simulate(SimConfig(robot="ur5", poses=1500, test_poses=300, seed=3))


def test_plan_end_to_end_into_calibrate(campaign, tmp_path):
    cand = tmp_path / "candidates.csv"
    write_measurements(cand, campaign.train)
    out = tmp_path / "plan" / "poses.csv"
    assert main(["plan", "--robot", "ur5", "--candidates", str(cand), "--n", "40", "--out", str(out), "--quiet"]) == 0
    planned = read_measurements(out, dof=6, require_positions=False)
    assert planned.n == 40 and planned.p is None
    # every planned pose is one of the candidates (bit-identical: the files are written with repr)
    rows = {tuple(r) for r in campaign.train.q.tolist()}
    assert all(tuple(r) in rows for r in planned.q.tolist())
    summary = json.loads((tmp_path / "plan" / "poses.plan.json").read_text())
    assert summary["k"] == 40 and summary["n_candidates"] == 1500 and summary["method"] == "auto"
    assert summary["n_spread"] == 10  # the ten picks after the geometry's 30 follow the candidates
    assert [c["k"] for c in summary["curve"]][-1] == 80
    assert summary["predicted_holdout_rmse_mm"] > 0 and summary["parameters"]
    assert (tmp_path / "plan" / "poses.plan.md").read_text().startswith("# written_by: torchcal plan")
    # measure the planned poses with the simulator's true model, then calibrate them
    with torch.no_grad():
        p = campaign.model(Context(q=planned.q)) + 15e-6 * torch.randn(
            40, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64
        )
    meas = tmp_path / "measured.csv"
    write_measurements(meas, Measurements(q=planned.q, p=p))
    run = tmp_path / "run"
    assert main(["calibrate", str(meas), "--robot", "ur5", "--method", "kinematic", "--out", str(run), "--quiet"]) == 0
    # plan again over the same file: its own earlier outputs are replaced without --force
    assert main(["plan", "--robot", "ur5", "--candidates", str(cand), "--n", "10", "--out", str(out), "--quiet"]) == 0
    # and with the run: its model and stochastic model, sampled candidates
    out2 = tmp_path / "again.csv"
    code = main(["plan", "--run", str(run), "--n", "20", "--pool", "500", "--out", str(out2), "--quiet"])
    assert code == 0 and read_measurements(out2, dof=6, require_positions=False).n == 20


def test_candidates_of_several_probes_are_poses_once(tmp_path, capsys):
    """own: a candidates file of 20 poses measured with two probes (a row per probe and pose) was planned as 40
    poses, --n 30 giving 10 poses twice; each pose counts once, and --n 30 is refused as more than the 20 poses."""
    q = sample_joints(load_robot("ur5"), 20, torch.Generator().manual_seed(0))
    rows = Measurements(q=q.repeat_interleave(2, dim=0), probe=torch.tensor([0, 1] * 20), probe_names=("A", "B"))
    write_measurements(tmp_path / "cand.csv", rows)
    argv = ["plan", "--robot", "ur5", "--candidates", str(tmp_path / "cand.csv"), "--out", str(tmp_path / "p.csv")]
    assert main([*argv, "--n", "30"]) == 2 and "more than the 20 candidates" in capsys.readouterr().err
    assert main([*argv, "--n", "12"]) == 0
    assert "20 candidate rows repeat another row's joints" in capsys.readouterr().err
    planned = read_measurements(tmp_path / "p.csv", dof=6, require_positions=False)
    assert planned.n == 12 and len(torch.unique(planned.q, dim=0)) == 12


def test_plan_refuses_what_it_cannot_do(tmp_path):
    assert main(["plan", "--n", "5", "--out", str(tmp_path / "x.csv"), "--quiet"]) == 2  # no robot
    model = MeasurementModel(load_robot("ur5"))
    q = sample_joints(model.robot, 50, torch.Generator().manual_seed(0))
    with pytest.raises(OptionError, match="1 to 50"):
        plan_poses(model, q, PlanOptions(k=51))
    with pytest.raises(OptionError, match="edge_share"):
        plan_poses(model, q, PlanOptions(k=5, edge_share=0.7))


def test_edge_share_is_kept(campaign):
    model = MeasurementModel(load_robot("ur5"))
    plan = plan_poses(model, campaign.train.q, PlanOptions(k=50, edge_share=0.2))
    assert int(plan.edge[4::5].sum()) == 10  # every fifth pick is an edge pose


def _discrepancy(a: torch.Tensor, b: torch.Tensor, length: float = 0.25) -> float:
    """Squared maximum mean discrepancy between two sets of scaled joints (squared-exponential kernel)."""

    def k(x, y):
        return torch.exp(-0.5 * torch.cdist(x, y).square() / length**2).mean()

    return float(k(a, a) + k(b, b) - 2 * k(a, b))


def test_a_design_for_a_learned_correction_follows_the_candidates_after_the_geometry(campaign):
    """Planned for the default method: the first picks are the criterion's, every later one but the edges' follows
    the candidates' density, closer to it than a random design of the same size or the kinematic design."""
    from torchcal.use.plan import GEOMETRY_PICKS, LEARNED_LENGTH, _scaled

    assert PlanOptions.for_method("kinematic", 10) == PlanOptions(k=10)
    auto = PlanOptions.for_method("auto", 150, spread_share=None, seed=3)
    assert (auto.spread_from, auto.spread_share, auto.edge_share, auto.seed) == (GEOMETRY_PICKS, 1.0, 0.02, 3)
    assert auto.spread_length == LEARNED_LENGTH < PlanOptions(k=1).spread_length
    assert PlanOptions.for_method("pcm", 150, edge_share=0.1).edge_share == 0.1  # what is given is kept
    model = MeasurementModel(load_robot("ur5"))
    q = campaign.train.q
    plan = plan_poses(model, q, auto)
    assert not bool(plan.spread[:GEOMETRY_PICKS].any())
    later = torch.arange(GEOMETRY_PICKS, 150)
    edge_turn = (later + 1) % 50 == 0
    assert bool(plan.spread[later[~edge_turn]].all()) and not bool(plan.spread[later[edge_turn]].any())
    assert plan.to_dict()["method"] == "auto" and plan.to_dict()["spread_from"] == GEOMETRY_PICKS
    where = _scaled(q)
    kinematic = plan_poses(model, q, PlanOptions.for_method("kinematic", 150))
    rnd = torch.randperm(len(q), generator=torch.Generator().manual_seed(0))[:150]
    d_auto, d_kin, d_rnd = (_discrepancy(where[i], where, LEARNED_LENGTH) for i in (plan.index, kinematic.index, rnd))
    print(f"discrepancy to the candidates: auto {d_auto:.2e}, kinematic {d_kin:.2e}, random {d_rnd:.2e}")
    assert d_auto < 0.9 * min(d_rnd, d_kin)
    assert "For the auto method" in plan.markdown() and "plan with --method auto" in kinematic.markdown()
    with pytest.raises(OptionError, match="spread_from"):
        plan_poses(model, q, PlanOptions(k=5, spread_from=-1))


def test_spread_picks_follow_the_work_poses_where_given(campaign, tmp_path):
    """Work poses in one half of joint 1's range: the spread picks after the geometry's go there, the file is read
    and named by the command, and a work file of the wrong robot is refused before anything is written."""
    q = campaign.train.q
    low = q[q[:, 0] < q[:, 0].median()]
    model = MeasurementModel(load_robot("ur5"))
    plan = plan_poses(model, q, PlanOptions.for_method("auto", 80), work=low)
    spread_q = plan.q[plan.spread]
    assert len(spread_q) >= 45 and float((spread_q[:, 0] < q[:, 0].median()).float().mean()) > 0.9
    assert plan.to_dict()["spread_toward"] == f"{len(low)} work poses"
    with pytest.raises(OptionError, match="work poses"):
        plan_poses(model, q, PlanOptions(k=5), work=low[:, :5])
    cand, work = tmp_path / "cand.csv", tmp_path / "work.csv"
    write_measurements(cand, campaign.train)
    write_measurements(work, Measurements(q=low))
    out = tmp_path / "poses.csv"
    argv = ["plan", "--robot", "ur5", "--candidates", str(cand), "--work", str(work), "--n", "40", "--out", str(out)]
    assert main([*argv, "--quiet"]) == 0
    assert json.loads((tmp_path / "poses.plan.json").read_text())["spread_toward"] == f"{len(low)} work poses"
    bad = tmp_path / "bad.csv"
    write_measurements(bad, Measurements(q=low[:, :5]))
    out2 = tmp_path / "other.csv"
    argv = ["plan", "--robot", "ur5", "--candidates", str(cand), "--work", str(bad), "--n", "40", "--out", str(out2)]
    assert main([*argv, "--quiet"]) == 2 and not out2.exists() and not (tmp_path / "other.plan.json").exists()


@pytest.mark.slow
def test_the_oracle_design_is_measured_beside_the_plan(campaign):
    res = compare("ur5", campaign.train, campaign.test, Protocol((30,), seeds=1, reference=None, oracle=True))
    (row,) = res["sizes"]
    assert row["oracle_mm"]["values"][0] > 0 and len(row["oracle_mm"]["values"]) == 1
    assert res["spread_from"] == 0 and res["spread_share"] == 0.5  # the kinematic design


def test_learned_share_goes_where_the_learned_correction_is_least_certain(campaign, monkeypatch):
    """A model whose learned correction is uncertain around one pose: every fifth pick goes there, spread by the
    discount, and the JSON counts them."""
    import torchcal.use.plan as plan_module

    q = campaign.train.q
    where = (q - q.min(0).values) / (q.max(0).values - q.min(0).values)
    d2 = (where - where[0]).square().sum(-1)

    def fake_std(model, ctx):
        return torch.exp(-d2 / 0.5).unsqueeze(-1).expand(-1, 3) * 1e-4

    monkeypatch.setattr(plan_module, "learned_std", fake_std)
    model = MeasurementModel(load_robot("ur5"))
    plan = plan_poses(model, q, PlanOptions(k=40, learned_share=0.2))
    assert int(plan.learned.sum()) == 8 and bool(plan.learned[2::5].all())
    assert int(plan.index[2]) == 0  # the first turn takes the most uncertain candidate
    picked = plan.index[plan.learned]
    assert len(set(picked.tolist())) == 8
    # the discount spreads them: no two of them closer than the nearest neighbours of the hot pose typically are
    w = where[picked]
    gaps = (w[:, None] - w[None]).norm(dim=-1) + torch.eye(8, dtype=w.dtype) * 9
    assert float(gaps.min()) > 0.05
    assert plan.to_dict()["n_learned"] == 8
    # without a learned correction (the real learned_std on a geometric model): no turns
    monkeypatch.undo()
    assert int(plan_poses(model, q, PlanOptions(k=20)).learned.sum()) == 0


@pytest.mark.slow
def test_predicted_holdout_error_within_25_percent(campaign):
    res = compare("ur5", campaign.train, campaign.test, Protocol((30, 100), seeds=1, reference=None))
    for row in res["sizes"]:
        print(row["k"], row["planned_mm"], row["predicted_mm"], row["random_mm"]["median"])
        assert 0.75 < row["predicted_over_measured"] < 1.25, row


@pytest.mark.slow
def test_plan_with_a_run_whose_learned_correction_has_a_predictive_sigma(tmp_path):
    """A simulated campaign with a smooth field the geometry lacks: the default method learns it (a GP), and plan
    --run --learned-share 0.2 sends every fifth pick where that correction is least certain (none by default)."""
    sim = tmp_path / "sim"
    assert (
        main(
            ["simulate", "--robot", "ur5", "--out", str(sim), "--poses", "500", "--test-poses", "50"]
            + ["--effect", "field=0.05mm", "--quiet"]
        )
        == 0
    )
    run = tmp_path / "run"
    assert main(["calibrate", str(sim / "train.csv"), "--robot", "ur5", "--out", str(run), "--quiet"]) == 0
    out = tmp_path / "poses.csv"
    argv = ["plan", "--run", str(run), "--n", "30", "--pool", "1000", "--out", str(out), "--learned-share", "0.2"]
    assert main([*argv, "--quiet"]) == 0
    d = json.loads((tmp_path / "poses.plan.json").read_text())
    assert d["n_learned"] == 6 and d["learned_share"] == 0.2
    assert d["method"] == "auto"  # the run's method: the design for a learned correction
    assert 0.5 < d["stochastic_model"]["variance_factor"] < 2.0
    assert main(["plan", "--run", str(run), "--n", "30", "--pool", "1000", "--out", str(out), "--quiet"]) == 0
    assert json.loads((tmp_path / "poses.plan.json").read_text())["n_learned"] == 0
    argv = ["plan", "--run", str(run), "--n", "40", "--pool", "1000", "--out", str(out), "--method", "kinematic"]
    assert main([*argv, "--quiet"]) == 0
    d = json.loads((tmp_path / "poses.plan.json").read_text())
    assert (d["method"], d["spread_share"], d["edge_share"]) == ("kinematic", 0.5, 0.1) and d["n_edge"] >= 4


def test_plan_for_one_station_of_a_several_station_run(tmp_path):
    """A run calibrated from two placements plans for the one named (its pose sets the line of sight), and refuses a
    station it does not have."""
    from torchcal.pipeline import Options, calibrate
    from torchcal.report.rundir import write_run

    c = simulate(SimConfig(robot="ur5", poses=120, test_poses=12, seed=4, stations=2))
    run_dir = write_run(calibrate("ur5", c.train, Options(method="kinematic", seed=4)), tmp_path / "run")
    rows = {}
    for st in ("S1", "S2"):
        out = tmp_path / f"{st}.csv"
        argv = ["plan", "--run", str(run_dir), "--station", st, "--n", "8", "--pool", "300", "--out", str(out)]
        assert main([*argv, "--quiet"]) == 0
        rows[st] = read_measurements(out, dof=6, require_positions=False).q
    assert rows["S1"].shape == rows["S2"].shape == (8, 6) and not torch.equal(rows["S1"], rows["S2"])
    bad = ["plan", "--run", str(run_dir), "--station", "S9", "--n", "8", "--out", str(tmp_path / "x.csv"), "--quiet"]
    assert main(bad) == 2 and not (tmp_path / "x.csv").exists() and not (tmp_path / "x.plan.json").exists()
