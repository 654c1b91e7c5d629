"""Re-stationing runs of every kind (issue 34, items 1 and 2): a default-method run with a named effect re-stationed
without the lever arm (it crashed: no kinematic column free), a run of two stations and two probes re-stationed on one
probe's points keeping every probe's lever arm, and ``predict`` honouring and keeping the ``station`` and ``probe``
columns of a re-stationed run."""

import json
from dataclasses import replace

import pytest
import torch

from tests.use.test_station import _placed, _rmse
from torchcal.cli import main
from torchcal.data import read_measurements, write_measurements
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.use.rundir import at_station


def _rows(m, key, name):
    names = getattr(m, f"{key}_names")
    return m.subset(torch.nonzero(getattr(m, key) == names.index(name)).flatten())


def _predict_rmse(run, rows, tmp_path, name):
    write_measurements(tmp_path / f"{name}.csv", rows)
    out = tmp_path / f"{name}_pred.csv"
    assert main(["predict", str(run), str(tmp_path / f"{name}.csv"), "--out", str(out), "--quiet"]) == 0
    got = read_measurements(out, require_positions=True)
    return _rmse((got.p - rows.p).norm(dim=-1)), got


@pytest.fixture(scope="module")
def default_two_stations(tmp_path_factory):
    """A default-method run of a two-station cell with a joint compliance (a named effect)."""
    cfg = SimConfig(
        robot="ur5", poses=200, test_poses=60, seed=5, stations=2, effects=[EffectSpec.parse("compliance:2=50um")]
    )
    c = simulate(cfg)
    run = calibrate("ur5", c.train, Options(method="auto", seed=5))
    return c, run, write_run(run, tmp_path_factory.mktemp("station_auto") / "run")


@pytest.mark.slow
def test_a_default_run_with_effects_is_restationed_within_1_5x_of_its_own_error(default_two_stations, tmp_path):
    c, run, run_dir = default_two_stations
    assert any(e.kind != "learned" for e in run.model.effects) or run.model.has_learned  # not a kinematic run
    own = _rmse(errors(run.model, _rows(c.test, "station", "S2"), trajectory=False))  # at S2, its own placement
    one, _, _ = at_station(c.model, "S2", None)  # the truth at S2 (its effects), moved to a new placement
    new, _ = _placed(c, (0.0, 0.0, 0.0), truth=one)
    idx = torch.randperm(new.n, generator=torch.Generator().manual_seed(0))  # 6 random points (10 draws: 1.01-1.26x)
    points, rest = new.subset(idx[:6]), new.subset(idx[6:])
    write_measurements(tmp_path / "pts.csv", points)
    assert main(["station", str(run_dir), str(tmp_path / "pts.csv"), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    e, _ = _predict_rmse(tmp_path / "r", rest, tmp_path, "rest")
    print(f"re-stationed default run: {e * 1e3:.4f} mm against its own {own * 1e3:.4f} mm at S2")
    assert e < 1.5 * own
    meta = json.loads((tmp_path / "r" / "model.json").read_text())
    assert meta["effects"] == [
        json.loads(json.dumps({"class": type(x).__name__, **x.config()}))
        for x in run.model.effects
        if type(x).__name__ != "GroupedCorrection"
    ]


@pytest.mark.slow
def test_a_restationed_run_keeps_every_probe_and_predict_keeps_the_columns(tmp_path):
    """Issue 34 item 2: 2 stations x 2 probes with orientation, kinematic; re-stationed on 6 points of S2 measured
    with P1, ``predict`` on S2's other rows gave P2 rows 100 mm off and dropped the probe column."""
    c = simulate(
        SimConfig(robot="ur5", poses=120, test_poses=40, seed=4, stations=2, probes=2, orientation_sigma_deg=0.01)
    )
    run = calibrate("ur5", c.train, Options(method="kinematic", seed=4))
    run_dir = write_run(run, tmp_path / "run")
    s2 = _rows(c.test, "station", "S2")
    p1 = torch.nonzero(s2.probe == s2.probe_names.index("P1")).flatten()
    pick = p1[:6]
    rest = s2.subset(torch.tensor([i for i in range(s2.n) if i not in set(pick.tolist())]))
    write_measurements(tmp_path / "pts.csv", s2.subset(pick))
    assert main(["station", str(run_dir), str(tmp_path / "pts.csv"), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    own = _rmse(errors(run.model, s2, trajectory=False))
    e, got = _predict_rmse(tmp_path / "r", rest, tmp_path, "rest")
    for probe in ("P1", "P2"):
        rows = torch.tensor([rest.probe_names[int(i)] == probe for i in rest.probe])
        e_p = _rmse((got.p[rows] - rest.p[rows]).norm(dim=-1))
        print(f"{probe}: {e_p * 1e3:.4f} mm (own at S2 {own * 1e3:.4f} mm)")
        assert e_p < 1.5 * own
    # the output keeps the columns, row by row
    assert got.probe is not None and got.station is not None
    assert [got.probe_names[int(i)] for i in got.probe] == [rest.probe_names[int(i)] for i in rest.probe]
    assert set(got.station_names) == {"S2"}
    # rows of another station, or of a probe the run lacks: refused with the file, line and column, nothing written
    s1 = _rows(c.test, "station", "S1").subset(torch.arange(3))
    write_measurements(tmp_path / "s1.csv", s1)
    out = tmp_path / "s1_pred.csv"
    assert main(["predict", str(tmp_path / "r"), str(tmp_path / "s1.csv"), "--out", str(out), "--quiet"]) == 2
    assert not out.exists()
    bad = replace(rest, probe_names=tuple("P9" if n == "P2" else n for n in rest.probe_names))
    write_measurements(tmp_path / "p9.csv", bad)
    assert main(["predict", str(tmp_path / "r"), str(tmp_path / "p9.csv"), "--out", str(out), "--quiet"]) == 2
    assert not out.exists()


def test_predict_refusal_names_file_line_and_column(tmp_path, capsys):
    c = simulate(SimConfig(robot="ur5", poses=60, test_poses=20, seed=2, probes=2))
    run_dir = write_run(calibrate("ur5", c.train, Options(method="kinematic", seed=2)), tmp_path / "run")
    bad = replace(c.test, probe_names=("P1", "P9"))
    write_measurements(tmp_path / "bad.csv", bad)
    code = main(["predict", str(run_dir), str(tmp_path / "bad.csv"), "--out", str(tmp_path / "o.csv")])
    err = capsys.readouterr().err
    first = next(i for i in range(bad.n) if int(bad.probe[i]) == 1)
    line = read_measurements(tmp_path / "bad.csv").lines[first]  # the file's line of the first P9 row
    assert code == 2 and f"bad.csv, line {line}, column 'probe'" in err and not (tmp_path / "o.csv").exists()


def test_a_learned_corrections_fallback_moves_with_the_instrument():
    """The integrated method's gate fades to a fallback geometry, whose prediction lived in tracker coordinates at the
    old placement: re-stationed (:func:`one_placement`), the whole prediction moves rigidly with the instrument."""
    import copy

    from torchcal.effects import Context, MeasurementModel
    from torchcal.effects.learned import CorrectionNet, LearnedEffect
    from torchcal.effects.region import RegionGate
    from torchcal.robot import load_robot
    from torchcal.robot import transforms as tf
    from torchcal.use.station import one_placement

    torch.manual_seed(0)
    robot = load_robot("ur5")
    fallback = copy.deepcopy(robot)
    with torch.no_grad():  # the fallback: a slightly different geometry and instrument pose, as a kinematic fit's
        fallback.geometry.delta.add_(1e-3 * torch.randn_like(fallback.geometry.delta))
        fallback.instrument.delta.add_(torch.tensor([1e-3, -2e-3, 1e-3, 1e-3, 0.0, -1e-3], dtype=torch.float64))
    q = (torch.rand(40, 6, dtype=torch.float64) - 0.5) * 4
    gate = RegionGate(LearnedEffect(CorrectionNet(6, 8)), q[:10], 0.5, fallback=fallback)
    model = MeasurementModel(robot, [gate])
    one, meta, _ = one_placement(model, {"effects": []}, None)
    assert meta["effects"][0]["fallback_frame"] == "base"
    ctx = Context(q=q[10:])  # mostly away from the support: the fallback carries these predictions
    with torch.no_grad():
        before = one(ctx)
        K = torch.tensor([[0, -0.7, 0], [0.7, 0, 0], [0, 0, 0.0]], dtype=torch.float64)
        M = tf.homogeneous(torch.linalg.matrix_exp(K), torch.tensor([0.5, -1.2, 0.3], dtype=torch.float64))
        torch.testing.assert_close(before, model(ctx))  # tying the fallback to the base changes nothing in place
        one.robot.instrument.set_matrix(M @ one.robot.instrument.matrix())
        model.robot.instrument.set_matrix(M @ model.robot.instrument.matrix())
        moved = tf.transform_points(M, before)
        torch.testing.assert_close(one(ctx), moved)  # rigidly with the instrument
        assert float((model(ctx) - moved).norm(dim=-1).max()) > 1e-4  # the untied fallback stayed behind
