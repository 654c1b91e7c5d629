"""Gross errors found in campaigns of several stations or probes (issue 47 item 10): the screening skipped them ("it
fits a single instrument pose and lever arm"), so a row in millimetres or a shifted point went into the fit. Each
pair of a station and a probe starts as a rigid body of its own; the rows the screening rejects are named by their
file lines, positions and orientations alike, and a clean campaign loses no row."""

import dataclasses
import math

import pytest
import torch

from experiments.gross_errors import contaminate
from torchcal.pipeline import Options, calibrate
from torchcal.sim import SimConfig, simulate

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _run(cfg: SimConfig, rows: list[int], mode: str = "shift", size: float = 0.005, rotate_deg: float = 0.0):
    c = simulate(cfg)
    data = c.train
    if rows and rotate_deg == 0.0:
        data = contaminate(data, torch.tensor(rows), mode=mode, size=size)
    elif rows:
        r = data.r.clone()
        r[rows, 0] += math.radians(rotate_deg)
        data = dataclasses.replace(data, r=r)
    run = calibrate("ur5", data, Options(method="kinematic"))
    s = run.screening
    assert s is not None, "the screening ran"
    named = sorted(x.line for part in (s.training, s.holdout) for x in part.rejected)
    turned = sorted(x.line for part in (s.training, s.holdout) for x in part.orientation_dropped)
    return data, named, turned


STATIONS = SimConfig(robot="ur5", poses=80, test_poses=10, seed=5, stations=2)
PROBES = SimConfig(robot="ur5", poses=40, test_poses=10, seed=5, probes=2)


@pytest.mark.parametrize("cfg", [STATIONS, PROBES], ids=["stations", "probes"])
def test_a_clean_campaign_loses_no_row(cfg):
    _, named, turned = _run(cfg, [])
    assert named == [] and turned == []


@pytest.mark.parametrize("cfg", [STATIONS, PROBES], ids=["stations", "probes"])
@pytest.mark.parametrize("mode", ["shift", "mm"])
def test_gross_rows_are_named_by_their_lines(cfg, mode):
    """A 5 mm shift and a row typed in millimetres, one in each station (or probe): both found, none else."""
    c = simulate(cfg)
    label = c.train.station if cfg.stations > 1 else c.train.probe
    rows = [int(torch.nonzero(label == k).flatten()[3]) for k in (0, 1)]
    data, named, _ = _run(cfg, rows, mode=mode)
    assert named == sorted(int(data.lines[i]) for i in rows)


@pytest.mark.parametrize(
    "cfg",
    [
        SimConfig(robot="ur5", poses=60, test_poses=10, seed=6, stations=2, orientation_sigma_deg=0.01),
        SimConfig(robot="ur5", poses=30, test_poses=6, seed=6, probes=2, orientation_sigma_deg=0.01),
    ],
    ids=["stations", "probes"],
)
def test_gross_orientations_are_left_out_per_station_and_probe(cfg):
    """The probe frame each row's orientation gives is taken in its own station's frame and against its own probe's
    frame: two rows turned by 40 deg are left out (their positions kept), no other."""
    data, named, turned = _run(cfg, [12, 40], rotate_deg=40.0)
    assert named == [] and turned == sorted(int(data.lines[i]) for i in (12, 40))
