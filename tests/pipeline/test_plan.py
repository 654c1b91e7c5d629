"""``torchcal plan`` (torchcal.pipeline.plan): the command end to end into a calibration, and the predicted held-out
error against the measured one on a simulated campaign."""

import json

import pytest
import torch

from torchcal.cli import main
from torchcal.data import Measurements, read_measurements, write_measurements
from torchcal.effects import Context
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.experiments.plan_poses import Protocol, compare
from torchcal.pipeline.plan import PlanOptions, plan_poses
from torchcal.robot import load_robot
from torchcal.sim import SimConfig, simulate
from torchcal.sim.poses import sample_joints


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
    assert summary["k"] == 40 and summary["n_candidates"] == 1500
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


def test_learned_share_goes_where_the_learned_correction_is_least_certain(campaign, monkeypatch):
    """A model whose learned correction is uncertain around one pose: every fifth pick goes there, spread by the
    discount, and the JSON counts them."""
    import torchcal.pipeline.plan as plan_module

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


def test_predicted_holdout_error_within_25_percent(campaign):
    res = compare("ur5", campaign.train, campaign.test, Protocol((30, 100), seeds=1, reference=None))
    for row in res["sizes"]:
        print(row["k"], row["planned_mm"], row["predicted_mm"], row["random_mm"]["median"])
        assert 0.75 < row["predicted_over_measured"] < 1.25, row


def test_plan_with_a_run_whose_learned_correction_has_a_predictive_sigma(tmp_path):
    """A simulated campaign with a smooth field the geometry lacks: the default method learns it (a GP), and plan
    --run sends every fifth pick where that correction is least certain."""
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
    assert main(["plan", "--run", str(run), "--n", "30", "--pool", "1000", "--out", str(out), "--quiet"]) == 0
    d = json.loads((tmp_path / "poses.plan.json").read_text())
    assert d["n_learned"] == 6 and d["learned_share"] == 0.2
    assert 0.5 < d["stochastic_model"]["variance_factor"] < 2.0
    assert (
        main(
            ["plan", "--run", str(run), "--n", "30", "--pool", "1000", "--out", str(out), "--learned-share", "0"]
            + ["--quiet"]
        )
        == 0
    )
    assert json.loads((tmp_path / "poses.plan.json").read_text())["n_learned"] == 0


def test_plan_for_one_station_of_a_several_station_run(tmp_path):
    """A run calibrated from two placements plans for the one named (its pose sets the line of sight), and refuses a
    station it does not have."""
    from torchcal.pipeline import Options, calibrate
    from torchcal.report import write_run

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
