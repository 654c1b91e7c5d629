"""Every command on every kind of run it accepts (issue 34, "What to build" 1): a user's chain ``calibrate ->
predict -> compensate -> station -> calibrate --prior -> plan --run`` on small simulated cells, each step judged
against the simulated truth, not only its exit status.

A cell is a robot, a method and a set-up:

* robots: ``ur5`` (revolute), ``ur10_track`` (a prismatic track under a UR10), ``fanuc_like`` (a ``readings:`` map:
  the elbow's model angle is ``-(J2 + J3)``, the wrist's readings reversed; ``tests/robot/data``);
* methods: ``kinematic``, ``auto`` (the default), ``pcm``, ``kinematic+ann``, ``integrated`` (``--engine
  adaptive``: the shortest of its engines);
* set-ups: one station and one probe, or two stations and two probes on a nest, each with or without a 6-D probe's
  orientation ``rx,ry,rz``; ``integrated`` needs a continuous trajectory, which has one station and one probe.

The full product (5 x 4 x 3) is 60 calibrations, about 15 minutes on two cores: too slow for the suite. The ten
cells of :data:`CELLS` (about 90 s of one core in all) cover every method with one and with several stations
(``integrated``: its trajectory, and its refusal of static poses and of several stations), every robot with one and
with several stations, with and without orientation, and every set-up on ``ur5``; the default method, the one users
run, on all three robots:

=========  ==================================  ===================================
robot      one station and probe               two stations and two probes
=========  ==================================  ===================================
ur5        auto; kinematic+ann (+rx);          kinematic (+rx); auto (+rx); pcm
           integrated (trajectory)
track      kinematic (+rx)                     auto
fanuc      auto                                kinematic (+rx)
=========  ==================================  ===================================

Each cell has an injected joint-2 compliance (50 um; 200 um on ``ur5-auto-one``, where the loop then names it,
the run of the default method with an effect that issue 34 item 1 re-stations). A cell is
simulated and calibrated once and shared by the step tests (and by pytest-xdist's workers: :func:`build`).

What each step must give, against the truth (``simulate``'s own measured test points and its true model, the
campaign simulated again in Python from the same seed, checked equal to the files):

* ``predict`` on the calibrated stations' held-out rows: within 3x the run's held-out RMSE (``rmse_after_mm``) per
  station and probe (a 6-D probe's orientation within 3x the run's held-out orientation error), the ``station`` and
  ``probe`` columns kept;
* ``compensate`` of those rows' measured points (their station and probe per row): the true robot at the commanded
  joints puts each row's probe within 3x the held-out RMSE of its target, the columns kept;
* ``station`` on 6 points of a placement the run never saw (measured with the first probe): ``predict`` of that
  placement's other rows, every probe, within 3x the held-out RMSE;
* ``calibrate --prior`` on 10 poses whose joint readings shifted by 2 mrad: the update predicts the shifted check
  rows within 2x the run's own error on them before the shift, and names the shifted joint's offset as moved;
* ``plan --run``: 8 poses within the joint limits, whose predicted held-out error is below that of 8 random
  candidates.

A combination that cannot be supported must exit 2 with the reason (``test_refused``), never 1. The cells that
fail today for a bug owned elsewhere are ``xfail(strict=True)`` with the bug named (:data:`XFAIL`): when the fix
is merged they fail, which says to remove the mark.
"""

from __future__ import annotations

import csv
import fcntl
import json
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
import torch

from torchcal._threads import torch_threads
from torchcal.cli import main
from torchcal.data import Measurements, read_measurements, write_measurements
from torchcal.effects import Context
from torchcal.robot import load_robot
from torchcal.robot import transforms as tf
from torchcal.sim import EffectSpec, SimConfig, simulate

pytestmark = pytest.mark.usefixtures("one_thread")

FANUC = str(Path(__file__).resolve().parents[1] / "robot" / "data" / "fanuc_like.yaml")
EFFECT = "compliance:2=50um"
#: how far a step's result may be from the truth, in the run's held-out RMSE (noise and a small cell's spread)
FACTOR = 3.0
#: the reading shift of the prior's rows [rad] and how many poses update the prior
SHIFT, PRIOR_POSES = 2e-3, 10
#: points that re-station a run, measured with its first probe
STATION_POINTS = 6


@dataclass(frozen=True)
class Setup:
    """How a cell is measured.

    Attributes:
        stations: instrument placements calibrated; the simulation places one more, the new placement that
            ``station`` re-stations on (none on a trajectory: its points are then the calibrated placement's).
        probes: reflectors on the nest, every pose measured by each.
        orientation: a 6-D probe: rows carry ``rx,ry,rz``.
        trajectory: a continuous trajectory (``integrated``) instead of static poses.
    """

    stations: int
    probes: int
    orientation: bool = False
    trajectory: bool = False


SETUPS = {
    "one": Setup(1, 1),
    "one+rx": Setup(1, 1, orientation=True),
    "several": Setup(2, 2),
    "several+rx": Setup(2, 2, orientation=True),
    "trajectory": Setup(1, 1, trajectory=True),
}


@dataclass(frozen=True)
class Cell:
    """A robot, a method and a set-up; ``shift`` is the reading (1-based) the prior's rows shift and ``moved`` the
    parameter the update must name (None: a readings map spreads the shift over two model joints); ``effect`` the
    one injected (``simulate --effect``)."""

    robot: str
    method: str
    setup: str
    seed: int
    shift: int = 2
    moved: str | None = "theta2"
    options: tuple[str, ...] = ()
    effect: str = EFFECT


CELLS = {
    "ur5-kinematic-several+rx": Cell("ur5", "kinematic", "several+rx", 1),
    # a compliance the loop names on 32 poses: the default method's run with an effect, re-stationed (issue 34 item 1)
    "ur5-auto-one": Cell("ur5", "auto", "one", 2, effect="compliance:2=200um"),
    "ur5-auto-several+rx": Cell("ur5", "auto", "several+rx", 3),
    "ur5-pcm-several": Cell("ur5", "pcm", "several", 4),
    "ur5-kinematic+ann-one+rx": Cell("ur5", "kinematic+ann", "one+rx", 5),
    "ur5-integrated-trajectory": Cell("ur5", "integrated", "trajectory", 6),
    "track-auto-several": Cell("ur10_track", "auto", "several", 7, shift=3, moved="theta3"),
    "track-kinematic-one+rx": Cell("ur10_track", "kinematic", "one+rx", 8, shift=3, moved="theta3"),
    "fanuc-kinematic-several+rx": Cell(FANUC, "kinematic", "several+rx", 9, moved=None),
    "fanuc-auto-one": Cell(FANUC, "auto", "one", 10, moved=None),
}

SEVERAL = [name for name, cell in CELLS.items() if SETUPS[cell.setup].stations > 1]
#: the bugs that fail cells today, each owned by another branch (issue 34); how to reproduce each: the report of
#: the branch that added this module
XFAIL: dict[tuple[str, str], str] = {}

STEPS = ("calibrate", "predict", "compensate", "station", "prior", "plan")


#: the cells the fast tier (``make test``) runs: one kinematic, one default and one PCM run of the UR5, every step of
#: each; the others (a trajectory, the track, the FANUC, orientations with the learned model) only in ``make test-all``
FAST = {"ur5-kinematic-several+rx", "ur5-auto-one", "ur5-pcm-several"}


def cells(step: str) -> list:
    """The cells as parameters of ``step``'s test, those of :data:`XFAIL` marked strict, those not in :data:`FAST`
    marked slow."""
    out = []
    for name in CELLS:
        marks = [] if name in FAST else [pytest.mark.slow]
        if (name, step) in XFAIL:
            marks.append(pytest.mark.xfail(strict=True, reason=XFAIL[name, step]))
        out.append(pytest.param(name, marks=marks))
    return out


# ------------------------------------------------------------------------------------------------- the cells


def _sim_config(cell: Cell) -> SimConfig:
    """What ``simulate`` is asked for the cell, as the CLI builds it (checked against the files it writes)."""
    s = SETUPS[cell.setup]
    if s.trajectory:
        size = dict(trajectory=True, path="multisine", samples=200, train_samples=160)
    else:  # 40 poses per placement, one placement more than calibrated (the new one of `station`)
        size = dict(poses=40 * (s.stations + 1), test_poses=20 * (s.stations + 1), stations=s.stations + 1)
    return SimConfig(
        robot=cell.robot,
        seed=cell.seed,
        effects=[EffectSpec.parse(cell.effect)],
        probes=s.probes,
        orientation_sigma_deg=0.01 if s.orientation else None,
        **size,
    )


def _simulate_args(cell: Cell, out: Path) -> list[str]:
    cfg = _sim_config(cell)
    args = ["simulate", "--robot", cfg.robot, "--out", str(out), "--seed", str(cfg.seed), "--effect", cell.effect]
    if cfg.trajectory:
        args += ["--trajectory", "--path", cfg.path, "--samples", str(cfg.samples)]
        args += ["--train-samples", str(cfg.train_samples)]
    else:
        args += ["--poses", str(cfg.poses), "--test-poses", str(cfg.test_poses), "--stations", str(cfg.stations)]
    if cfg.probes > 1:
        args += ["--probes", str(cfg.probes)]
    if cfg.orientation_sigma_deg is not None:
        args += ["--orientation", str(cfg.orientation_sigma_deg)]
    return [*args, "--quiet"]


def _only(m: Measurements, stations: int, drop_station: bool) -> Measurements:
    """The rows of ``m`` measured from its first ``stations`` placements (or, with ``stations`` negative, from the
    last), without a station column where ``drop_station`` (a file of one placement, as a user has it)."""
    if m.station is None:
        return m
    keep = m.station < stations if stations > 0 else m.station == len(m.station_names) - 1
    out = m.subset(torch.nonzero(keep).flatten())
    return replace(out, station=None, station_names=()) if drop_station else out


@dataclass
class Built:
    """A cell simulated and calibrated: its true model, its held-out rows and what the run says of itself. Its
    folder is shared by the tests (and by pytest-xdist's workers): they read it and write into their own."""

    cell: Cell
    campaign: object  # torchcal.sim.Campaign: the true model and joints
    near: Measurements  # held-out rows of the calibrated placements
    far: Measurements  # held-out rows of the placement the run never saw (a trajectory: the calibrated one)
    run: Path
    report: dict

    @property
    def held_out_mm(self) -> float:
        return float(self.report["rmse_after_mm"])


def _write(path: Path, m: Measurements) -> Path:
    write_measurements(path, m)
    return path


def _calibrate_cell(cell: Cell, root: Path) -> None:
    """``simulate`` the cell into ``root/sim``, keep the calibrated placements' rows and ``calibrate`` them into
    ``root/run``."""
    s = SETUPS[cell.setup]
    assert main(_simulate_args(cell, root / "sim")) == 0
    train = _only(read_measurements(root / "sim" / "train.csv"), s.stations, s.stations == 1)
    data = _write(root / "train.csv", train)
    args = ["calibrate", str(data), "--robot", cell.robot, "--method", cell.method, "--out", str(root / "run")]
    assert main([*args, "--seed", "1", *cell.options, "--quiet"]) == 0


def _load_cell(cell: Cell, root: Path) -> Built:
    """A calibrated cell, its truth simulated again in Python from the same seed and checked against the files."""
    s = SETUPS[cell.setup]
    cfg = _sim_config(cell)
    campaign = simulate(cfg)
    train = read_measurements(root / "sim" / "train.csv")
    test = read_measurements(root / "sim" / "test.csv")
    assert torch.equal(train.q, campaign.train.q) and torch.equal(test.p, campaign.test.p)
    near, far = _only(test, s.stations, s.stations == 1), _only(test, -1, True)
    report = json.loads((root / "run" / "report.json").read_text())
    return Built(cell, campaign, near, far, root / "run", report)


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """The cells by name, each simulated and calibrated once (one torch thread): under pytest-xdist in a folder
    the workers share, one calibrating a cell while the others wait for it (a lock per cell), as the xdist docs
    recommend for a fixture to run once."""
    base = tmp_path_factory.getbasetemp()
    shared = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "paths"
    shared.mkdir(exist_ok=True)
    done: dict[str, Built] = {}

    def get(name: str) -> Built:
        if name not in done:
            root = shared / name
            with open(shared / f"{name}.lock", "w") as lock, torch_threads(1):
                fcntl.flock(lock, fcntl.LOCK_EX)
                if not (root / "run" / "report.json").exists():
                    root.mkdir(exist_ok=True)
                    _calibrate_cell(CELLS[name], root)
                done[name] = _load_cell(CELLS[name], root)
        return done[name]

    return get


# ------------------------------------------------------------------------------------------------- helpers


def _rows(path: Path) -> list[dict]:
    with open(path, encoding="utf-8") as f:
        return list(csv.DictReader(line for line in f if not line.startswith("#")))


def _xyz(rows: list[dict]) -> torch.Tensor:
    return torch.tensor([[float(r[k]) for k in "xyz"] for r in rows], dtype=torch.float64)


def _groups(m: Measurements) -> dict[str, torch.Tensor]:
    """Row indices per (station, probe) label of ``m``: 'S1/P2', or 'all' where it has neither column."""
    st = [m.station_names[i] for i in m.station.tolist()] if m.station is not None else ["-"] * m.n
    pr = [m.probe_names[i] for i in m.probe.tolist()] if m.probe is not None else ["-"] * m.n
    keys = [f"{a}/{b}" for a, b in zip(st, pr, strict=True)]
    return {k: torch.tensor([i for i, x in enumerate(keys) if x == k]) for k in dict.fromkeys(keys)}


def _rmse_mm(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm(dim=-1).square().mean().sqrt()) * 1e3


def _assert_close_per_group(m: Measurements, got: torch.Tensor, limit_mm: float, what: str) -> None:
    """Every station/probe group of ``m`` within ``limit_mm`` RMSE of its measured points."""
    worst = {k: _rmse_mm(got[i], m.p[i]) for k, i in _groups(m).items()}
    assert max(worst.values()) <= limit_mm, f"{what}: RMSE per station/probe {worst} mm, limit {limit_mm:.4f} mm"


def _predict(run: Path, m: Measurements, root: Path, name: str) -> tuple[torch.Tensor, list[dict]]:
    data = root / f"{name}.csv"
    write_measurements(data, m)
    out = root / f"{name}.pred.csv"
    assert main(["predict", str(run), str(data), "--out", str(out), "--quiet"]) == 0
    rows = _rows(out)
    assert len(rows) == m.n
    return _xyz(rows), rows


def _assert_columns_kept(m: Measurements, rows: list[dict]) -> None:
    """The output's station and probe columns are the input's, row by row."""
    for key, idx, names in (("station", m.station, m.station_names), ("probe", m.probe, m.probe_names)):
        if idx is not None:
            assert key in rows[0], f"the {key} column was dropped"
            assert [r[key] for r in rows] == [names[i] for i in idx.tolist()]


def _truth_at(b: Built, q: torch.Tensor, m: Measurements) -> torch.Tensor:
    """Where the true robot puts each row's probe at joint readings ``q``, seen from the row's station ``(N, 3)``."""
    truth = b.campaign.model
    st = pr = None
    if m.station is not None:
        st = torch.tensor([truth.robot.stations.index(m.station_names[i]) for i in m.station.tolist()])
    elif truth.robot.stations:
        st = torch.zeros(m.n, dtype=torch.long)  # a file of one placement: the simulation's first
    if m.probe is not None:
        pr = torch.tensor([truth.robot.probes.index(m.probe_names[i]) for i in m.probe.tolist()])
    with torch.no_grad():
        return truth(Context(q=q, t=m.t, temperature=m.temperature, station=st, probe=pr))


# ------------------------------------------------------------------------------------------------- the steps


@pytest.mark.parametrize("name", cells("calibrate"))
def test_calibrate(build, name):
    """The run's method is the one asked for and it does not err more than the nominal model on held-out rows."""
    b = build(name)
    assert b.report["method"] == b.cell.method
    assert b.held_out_mm <= b.report["rmse_before_mm"], b.report


@pytest.mark.parametrize("name", cells("predict"))
def test_predict(build, name, tmp_path):
    """``predict`` on held-out rows of the calibrated placements, each with its station and probe (and a 6-D
    probe's orientation)."""
    b = build(name)
    got, rows = _predict(b.run, b.near, tmp_path, "near")
    _assert_close_per_group(b.near, got, FACTOR * b.held_out_mm, "predict")
    _assert_columns_kept(b.near, rows)
    if b.near.r is not None:  # a 6-D probe: the orientation too, against the run's held-out orientation error
        r = torch.tensor([[float(row[k]) for k in ("rx", "ry", "rz")] for row in rows], dtype=torch.float64)
        miss = tf.so3_log(tf.so3_exp(r).transpose(-1, -2) @ tf.so3_exp(b.near.r)).norm(dim=-1)
        rms_deg = math.degrees(float(miss.square().mean().sqrt()))
        assert rms_deg <= FACTOR * b.report["orientation"]["rms_after_deg"], rms_deg


@pytest.mark.parametrize("name", cells("compensate"))
def test_compensate(build, name, tmp_path):
    """``compensate`` of measured points, each in its row's station frame and for its row's probe, from the
    joints 20 mrad off (a start close enough for the nearest solution, far enough that staying there misses): the
    true robot at the commands puts the probe on the target."""
    b = build(name)
    g = torch.Generator().manual_seed(0)
    start = b.near.q + 0.02 * torch.randn(b.near.q.shape, generator=g, dtype=torch.float64)
    limits = load_robot(b.cell.robot).limits
    start = start.clamp(limits[:, 0], limits[:, 1])
    targets = _write(tmp_path / "targets.csv", replace(b.near, q=start))
    out = tmp_path / "joints.csv"
    assert main(["compensate", str(b.run), str(targets), "--out", str(out), "--quiet"]) == 0
    rows = _rows(out)
    assert len(rows) == b.near.n
    dof = b.near.q.shape[1]
    q = torch.tensor([[float(r[f"q{k}"]) for k in range(1, dof + 1)] for r in rows], dtype=torch.float64)
    reached = _truth_at(b, q, b.near)
    _assert_close_per_group(b.near, reached, FACTOR * b.held_out_mm, "the true robot at compensate's joints")
    _assert_columns_kept(b.near, rows)
    assert {r["status"] for r in rows} == {"converged"}


def _station_points(b: Built) -> tuple[Measurements, Measurements]:
    """6 points of the new placement measured with the first probe, spread over its rows (a trajectory's neighbouring
    samples span no volume), and that placement's other rows."""
    first = torch.nonzero(torch.ones(b.far.n, dtype=torch.bool) if b.far.probe is None else b.far.probe == 0)
    pick = first.flatten()[torch.linspace(0, len(first) - 1, STATION_POINTS).round().long()]
    rest = torch.ones(b.far.n, dtype=torch.bool)
    rest[pick] = False
    return b.far.subset(pick), b.far.subset(torch.nonzero(rest).flatten())


@pytest.mark.parametrize("name", cells("station"))
def test_station(build, name, tmp_path):
    """``station`` on 6 points of a placement the run never saw: the new run predicts that placement's other rows,
    every probe's, as well as the run predicts its own."""
    b = build(name)
    points, rest = _station_points(b)
    st = tmp_path / "restationed"
    assert main(["station", str(b.run), str(_write(tmp_path / "points.csv", points)), "--out", str(st), "--quiet"]) == 0
    got, rows = _predict(st, rest, tmp_path, "far")
    _assert_close_per_group(rest, got, FACTOR * b.held_out_mm, "predict after station")
    _assert_columns_kept(rest, rows)


def _shifted(m: Measurements, joint: int) -> Measurements:
    """``m`` with joint ``joint``'s readings (1-based) shifted by :data:`SHIFT`: the encoder re-mounted."""
    q = m.q.clone()
    q[:, joint - 1] += SHIFT
    return replace(m, q=q)


def _prior_rows(b: Built) -> tuple[Measurements, Measurements]:
    """The held-out rows split by pose: the rows of :data:`PRIOR_POSES` poses spread over them (a trajectory's
    neighbouring samples hardly move) update, the others check. A pose's rows (one per probe) are adjacent."""
    per_pose = 1 if b.near.probe is None else len(b.near.probe_names)
    poses = torch.arange(b.near.n) // per_pose
    picked = torch.linspace(0, int(poses[-1]), PRIOR_POSES).round().long()
    update = torch.isin(poses, picked)
    return b.near.subset(torch.nonzero(update).flatten()), b.near.subset(torch.nonzero(~update).flatten())


def _inside_after_shift(m: Measurements, cell: Cell) -> Measurements:
    """The rows of ``m`` whose shifted reading stays within the robot's limits (a reading beyond them is refused by
    the reader, as it should be)."""
    lo, hi = load_robot(cell.robot).limits[cell.shift - 1]
    q = m.q[:, cell.shift - 1] + SHIFT
    return m.subset(torch.nonzero((q >= lo) & (q <= hi)).flatten())


@pytest.mark.parametrize("name", cells("prior"))
def test_prior(build, name, tmp_path):
    """``calibrate --prior`` on 10 poses after joint ``shift``'s reading moved by 2 mrad: the update predicts the
    shifted rows as the run predicted them before the shift, and names the joint's offset as moved."""
    b, cell = build(name), CELLS[name]
    update, check = (_inside_after_shift(m, cell) for m in _prior_rows(b))
    own, _ = _predict(b.run, check, tmp_path, "check")
    own_mm = _rmse_mm(own, check.p)
    moved = _shifted(check, cell.shift)
    before, _ = _predict(b.run, moved, tmp_path, "moved")
    assert _rmse_mm(before, moved.p) > own_mm + 0.5  # the shift matters
    data = _write(tmp_path / "update.csv", _shifted(update, cell.shift))
    out = tmp_path / "updated"
    args = ["calibrate", str(data), "--robot", cell.robot, "--prior", str(b.run), "--out", str(out), "--quiet"]
    if cell.method == "pcm":  # its network corrects the nominal geometry, which an update moves: refused
        assert main(args) == 2 and not out.exists()
        return
    assert main(args) == 0
    after, _ = _predict(out, moved, tmp_path, "moved_after")
    assert _rmse_mm(after, moved.p) <= 2 * own_mm + 0.01, (_rmse_mm(after, moved.p), own_mm)
    prior = json.loads((out / "report.json").read_text())["prior"]
    if cell.moved is None:
        return
    # named: as moved, with the shift's size, or (issue 34 item 3) as what the rows cannot tell apart
    confounded = json.dumps({k: v for k, v in prior.items() if "confound" in k})
    assert cell.moved in prior["moved"] or cell.moved in confounded, prior
    if cell.moved in prior["moved"]:
        change = {p["name"]: p["change"] for p in prior["parameters"]}[cell.moved]
        assert change == pytest.approx(-SHIFT, rel=0.25)


@pytest.mark.parametrize("name", cells("plan"))
def test_plan(build, name, tmp_path):
    """``plan --run`` for the run's last station and probe: 30 poses in the joint limits that identify the
    parameters and that the plan predicts calibrate better than 30 random candidates (8 poses cannot identify them,
    and the plan says so instead of predicting an error: issue 35 item 2)."""
    b = build(name)
    out = tmp_path / "plan.csv"
    args = ["plan", "--run", str(b.run), "--n", "30", "--out", str(out), "--pool", "400", "--seed", "0"]
    s = SETUPS[b.cell.setup]
    if s.stations > 1:
        args += ["--station", f"S{s.stations}"]
    if s.probes > 1:
        args += ["--probe", f"P{s.probes}"]
    assert main([*args, "--quiet"]) == 0
    planned = read_measurements(out, require_positions=False)
    assert planned.n == 30
    limits = load_robot(b.cell.robot).limits
    assert bool(((planned.q >= limits[:, 0] - 1e-9) & (planned.q <= limits[:, 1] + 1e-9)).all())
    plan = json.loads(out.with_suffix(".plan.json").read_text())
    assert plan["identifies"] and math.isfinite(plan["predicted_holdout_rmse_mm"])
    assert plan["predicted_holdout_rmse_mm"] < plan["random_predicted_holdout_rmse_mm"]


# ------------------------------------------------------------------------------------------------- refusals


def test_refused_integrated_on_static_poses_of_several_stations(build, tmp_path, capsys):
    """``integrated`` on static poses from several stations and probes: exit 2 with the reason, nothing written."""
    b = build("ur5-pcm-several")
    out = tmp_path / "run"
    args = ["calibrate", str(b.run.parent / "train.csv"), "--robot", "ur5", "--method", "integrated", "--out", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "integrated" in err and "trajectory" in err
    assert not out.exists()


def test_refused_a_trajectory_of_several_stations(tmp_path, capsys):
    """A trajectory (what ``integrated`` needs) measured from several stations or probes: ``simulate`` refuses it
    with exit 2 and the reason, writing nothing (a trajectory is one placement's continuous record)."""
    for extra in (["--stations", "2"], ["--probes", "2"]):
        out = tmp_path / "sim"
        args = ["simulate", "--robot", "ur5", "--out", str(out), "--trajectory", "--samples", "50"]
        assert main([*args, "--train-samples", "40", *extra]) == 2
        assert "static poses" in capsys.readouterr().err and not out.exists()
