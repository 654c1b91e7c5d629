"""Beyond the calibrated region, the model that travels (torchcal.pipeline.beyond, issue 51): the rule, the bound of
the sigma by the tolerance priors, and predict's rows beyond the region given to the chosen model."""

import csv
import json
import math
import shutil

import pytest
import torch
from _cli import cli_simulate

from torchcal.cli import main
from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.pipeline import Options
from torchcal.pipeline.beyond import TIE, _simplest_best, bounded
from torchcal.robot import load_robot
from torchcal.use.rundir import MODEL_NAMES, load_model, load_nominal, row_trust

F64 = torch.float64


def _rows(path):
    with open(path, encoding="utf-8") as f:
        return list(csv.DictReader(line for line in f if not line.startswith("#")))


def test_a_richer_model_must_beat_a_simpler_one_by_more_than_the_tie():
    assert _simplest_best({"nominal": 1.0, "geometric": TIE * 1.001, "full": TIE * 1.0005}) == "nominal"
    assert _simplest_best({"nominal": 1.0, "geometric": 0.9, "full": 0.895}) == "geometric"
    assert _simplest_best({"nominal": 1.0, "geometric": 0.9, "full": 0.5}) == "full"
    assert _simplest_best({"full": 0.5}) == "full"


def test_the_sigma_beyond_is_bounded_by_the_tolerance_priors():
    """A geometric element held at the later fits' 1 mm prior is bounded to about the tolerance (0.1 mm): the
    information of both, ``1 / (1/1e-6 + 1/1e-8)``; an element of the instrument, uncorrelated, keeps its variance,
    and so does one already at its tolerance."""

    class Run:
        options = Options()

    model = MeasurementModel(load_robot("ur5"))
    geo = model.robot.geometry
    k = next(i for i, n in enumerate(geo.names) if n.startswith("d") and bool(geo.mask.flatten()[i]))
    inst = model.robot.instrument
    cov = ParameterCovariance(
        ["robot.geometry.delta", "robot.instrument.delta"],
        [[k], [0]],
        [geo.names[k], inst.names[0]],
        torch.diag(torch.tensor([1e-6, 4e-8], dtype=F64)),
    )
    out = bounded(cov, model, Run())
    tol = Run.options.fit.geometric().prior_length
    assert float(out.matrix[0, 0]) == pytest.approx(1 / (1 / 1e-6 + 1 / tol**2), rel=1e-9)
    assert float(out.matrix[1, 1]) == pytest.approx(4e-8, rel=1e-12)
    assert float(out.matrix[0, 1]) == 0.0
    # an element the kinematic calibration already held at its tolerance keeps it: the prior is not counted twice
    held = ParameterCovariance(cov.names, cov.index, cov.labels, torch.diag(torch.tensor([tol**2, 4e-8], dtype=F64)))
    assert torch.equal(bounded(held, model, Run()).matrix, held.matrix)


@pytest.fixture(scope="module")
def narrow_run(tmp_path_factory):
    """A kinematic calibration of a narrow campaign (joints 1, 4, 5, 6 within 1 deg) with a compliance of joint 2."""
    root = tmp_path_factory.mktemp("beyond")
    assert cli_simulate(root / "sim", "--poses", "120", "--test-poses", "30", "--seed", "3", "--narrow", "1,4,5,6",
                        "--width-deg", "1", "--effect", "compliance:2=1.5e-5rad/Nm") == 0  # fmt: skip
    assert main(["calibrate", str(root / "sim" / "train.csv"), "--robot", "ur5", "--method", "kinematic",
                 "--out", str(root / "run"), "--seed", "1", "--quiet"]) == 0  # fmt: skip
    return root


def test_the_run_keeps_the_nominal_model_and_says_what_it_chose(narrow_run):
    run = narrow_run / "run"
    meta = json.loads((run / "model.json").read_text(encoding="utf-8"))
    beyond = meta["beyond"]
    assert beyond["model"] in MODEL_NAMES and beyond["n_evidence"] >= 10
    assert set(beyond["rmse_mm"]) == {"full", "nominal"}  # a kinematic run: its model and the nominal one
    best = min(beyond["rmse_mm"].values())
    assert beyond["rmse_mm"][beyond["model"]] <= best / TIE + 1e-12
    report = json.loads((run / "report.json").read_text(encoding="utf-8"))
    assert report["trust"]["beyond"]["model"] == beyond["model"]
    assert f"(`model` = {beyond['model']}) predicts every row" in (run / "report.md").read_text(encoding="utf-8")
    model, meta = load_model(run)
    nom, cov, tr = load_nominal(run, model, meta)
    assert cov is not None and tr.n > 0
    # the nominal model is the nominal geometry: its geometric corrections are all zero
    assert float(nom.robot.geometry.delta.detach().abs().max()) == 0.0


def test_predict_gives_the_rows_beyond_to_the_chosen_model_with_its_own_sigma(narrow_run, tmp_path):
    """The run made to choose the nominal model: the test rows (all beyond the narrow region) are predicted by
    nominal.pt, the model column says ``nominal``, and their sigma is the nominal model's own."""
    run = tmp_path / "run"
    shutil.copytree(narrow_run / "run", run)
    meta = json.loads((run / "model.json").read_text(encoding="utf-8"))
    meta["beyond"]["model"] = "nominal"
    (run / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    test = narrow_run / "sim" / "test.csv"
    assert main(["predict", str(run), str(test), "--out", str(tmp_path / "p.csv"), "--quiet"]) == 0
    rows = _rows(tmp_path / "p.csv")
    assert {r["model"] for r in rows if float(r["extrapolation"]) > 0} == {"nominal"}
    model, meta = load_model(run)
    nom, cov, tr = load_nominal(run, model, meta)
    from torchcal.data import read_measurements

    data = read_measurements(test)
    ctx = Context.from_measurements(data)
    rt = row_trust(run, model, meta, ctx)
    out = torch.nonzero(rt.extrapolation > 0).flatten()
    with torch.no_grad():
        want = nom(ctx)
    got = torch.tensor([[float(r[c]) for c in "xyz"] for r in rows], dtype=F64)
    assert torch.allclose(got[out], want[out], atol=1e-9)
    s = torch.tensor([[float(r[c]) for c in ("sx", "sy", "sz")] for r in rows], dtype=F64)
    assert torch.allclose(s[out], tr.std(nom, ctx.subset(out), cov), rtol=1e-6)
    assert math.isfinite(float(s.max()))


def test_plan_with_a_narrow_run_proposes_poses_that_move_its_narrow_joints(narrow_run, tmp_path, capsys):
    """``plan --run`` of a run whose joints 1, 4, 5, 6 moved 1 deg: the candidates span those joints' limits (not
    the run's 1-deg band), so the planned poses move them; stderr names them."""
    from torchcal.use.plan import candidate_region

    model, _ = load_model(narrow_run / "run")
    region, narrow = candidate_region(model)
    assert narrow == [1, 4, 5, 6]
    assert torch.equal(region[:, 1], model.region[:, 1])  # a joint the run moved keeps its calibrated range
    assert torch.equal(region[:, 0], model.robot.limits[0])
    out = tmp_path / "plan.csv"
    assert main(["plan", "--run", str(narrow_run / "run"), "--n", "12", "--pool", "300", "--out", str(out)]) == 0
    assert "q1, q4, q5, q6, narrow in the run, over their limits" in capsys.readouterr().err
    rows = _rows(out)
    q = torch.tensor([[float(r[f"q{j}"]) for j in range(1, 7)] for r in rows], dtype=F64)
    spread = torch.rad2deg(q.max(dim=0).values - q.min(dim=0).values)
    assert bool((spread[[0, 3, 4, 5]] > 20).all()), spread


def test_compensate_commands_the_rows_beyond_with_the_chosen_model(narrow_run, tmp_path):
    """The run made to choose the nominal model: compensate solves the targets beyond the region with it (the nominal
    model puts the probe on each target at the commands) and its model column says ``nominal``."""
    from torchcal.data import read_measurements

    run = tmp_path / "run"
    shutil.copytree(narrow_run / "run", run)
    meta = json.loads((run / "model.json").read_text(encoding="utf-8"))
    meta["beyond"]["model"] = "nominal"
    (run / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    model, meta = load_model(run)
    nom = load_nominal(run, model, meta)[0]
    test = narrow_run / "sim" / "test.csv"
    q = read_measurements(test).q[:6]
    with torch.no_grad():
        targets = nom(Context(q=q))
    lines = ["x,y,z"] + [",".join(repr(float(v)) for v in row) for row in targets]
    (tmp_path / "targets.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    start = tmp_path / "start.csv"
    start.write_text("\n".join(["q1,q2,q3,q4,q5,q6"] + [",".join(repr(float(v)) for v in row) for row in q]) + "\n")
    assert main(["compensate", str(run), str(tmp_path / "targets.csv"), "--start", str(start),
                 "--out", str(tmp_path / "j.csv"), "--quiet"]) == 0  # fmt: skip
    rows = _rows(tmp_path / "j.csv")
    beyond = [k for k, r in enumerate(rows) if float(r["extrapolation"]) > 0]
    assert beyond and all(rows[k]["model"] == "nominal" for k in beyond)
    qj = torch.tensor([[float(r[f"q{j}"]) for j in range(1, 7)] for r in rows], dtype=F64)
    with torch.no_grad():
        miss = (nom(Context(q=qj)) - targets).norm(dim=1)
    assert float(miss[beyond].max()) < 1e-6
