"""Whether an export stands alone: the DH and URDF files of a default-method run, loaded alone as another program
would and re-registered to the instrument on the training rows, against the kinematic run's files.

For each campaign, the training rows are calibrated twice (``--method kinematic`` and the default), each run written
as a run directory and exported (``dh``, ``urdf``; the default run also with ``--geometry cofitted``, the geometry
fitted together with its effects). Each file is loaded with :func:`torchcal.load_robot` (a URDF to the flange, as
``--robot`` loads it), its instrument pose and lever arm fitted in closed form to the training rows
(:func:`torchcal.estimate.fit.place_instrument_and_tool`: what a user with other software does), and the test rows
are predicted. ``ratio`` is the default run's stand-alone file over the kinematic run's (target <= 1.05).

A campaign is a folder with ``train.csv`` and ``test.csv`` (the outside campaigns: a UR5 with a transmission-ratio
error, ``jointscale``, or gravity compliance), or a real UR10 series of ipa-robot-accuracy (its test rows:
calibrate's own held-out split, which the default run also chose its stand-alone geometry on).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import torch

from torchcal.data import Measurements, read_ipa, read_measurements
from torchcal.effects import MeasurementModel
from torchcal.estimate.fit import errors, place_instrument_and_tool
from torchcal.pipeline import Options, calibrate, holdout_split
from torchcal.report.rundir import write_run
from torchcal.robot import load_robot
from torchcal.robot.load import calibrated_flange
from torchcal.stats import rmse
from torchcal.use.export import export_run

MM = 1e3
SEED = 0
HOLDOUT = 0.2
FORMATS = ("dh", "urdf")


def file_alone(path: Path, train: Measurements, test: Measurements) -> float:
    """Held-out RMSE [mm] of the exported file ``path`` loaded alone and re-registered on ``train``'s rows."""
    tip = calibrated_flange(path) if path.suffix == ".urdf" else None
    robot = load_robot(path, tip_link=tip) if tip else load_robot(path)
    place_instrument_and_tool(robot, train.q, train.p)
    return rmse(errors(MeasurementModel(robot), test, trajectory=False)) * MM


def _exports(run_dir: Path, out: Path, train, test, geometries: tuple[str, ...]) -> dict:
    res = {}
    for geometry in geometries:
        for fmt in FORMATS:
            f = out / f"{run_dir.name}_{geometry}.{'yaml' if fmt == 'dh' else 'urdf'}"
            ex = export_run(run_dir, fmt, f, geometry=geometry)
            res[f"{fmt}_{geometry}_mm"] = file_alone(f, train, test)
            res[f"{geometry}_header_mm"] = ex.rmse_mm
            res[f"{geometry}_which"] = ex.which if ex.source is None else f"{ex.which} ({ex.source})"
    return res


def campaign(name: str, robot: str, train: Measurements, test: Measurements, tmp: Path) -> dict:
    """One campaign (module docstring)."""
    out = {"campaign": name, "robot": robot, "n_train": train.n, "n_test": test.n, "runs": {}}
    for method in ("kinematic", "auto"):
        t0 = time.perf_counter()
        run = calibrate(robot, train, Options.of(method=method, seed=SEED, holdout=HOLDOUT, trajectory=False))
        rd = write_run(run, tmp / f"{name}_{method}")
        geometries = ("standalone",) if method == "kinematic" else ("standalone", "cofitted")
        full = rmse(errors(run.model.to("cpu"), test, trajectory=False)) * MM
        out["runs"][method] = {
            "calibration_s": time.perf_counter() - t0,
            "effects": [e.label() for e in run.model.effects],
            "full_run_test_mm": full,
            **_exports(rd, tmp, train, test, geometries),
        }
    k, d = out["runs"]["kinematic"], out["runs"]["auto"]
    out["ratio"] = {fmt: d[f"{fmt}_standalone_mm"] / k[f"{fmt}_standalone_mm"] for fmt in FORMATS}
    out["ratio_cofitted"] = {fmt: d[f"{fmt}_cofitted_mm"] / k[f"{fmt}_standalone_mm"] for fmt in FORMATS}
    return out


def _ipa(data_dir: Path, series: str) -> tuple[Measurements, Measurements]:
    from experiments.ipa_series import series_file

    m = read_ipa(series_file(data_dir, series))
    split = holdout_split(m, HOLDOUT, SEED, trajectory=False)
    return m.subset(torch.sort(split.keep).values), m.subset(torch.sort(split.held).values)


def run(folders: list[Path], robot: str = "ur5", ipa: Path | None = None, series: tuple[str, ...] = ()) -> dict:
    """Every campaign of ``folders`` (on ``robot``) and each ipa-robot-accuracy ``series`` of ``ipa`` (a UR10)."""
    t0 = time.perf_counter()
    res = []
    with tempfile.TemporaryDirectory() as tmp:
        for f in folders:
            train, test = read_measurements(f / "train.csv"), read_measurements(f / "test.csv")
            res.append(campaign(f.name, robot, train, test, Path(tmp)))
        for s in series:
            train, test = _ipa(ipa, s)
            res.append(campaign(f"ipa_{s}", "ur10", train, test, Path(tmp)))
    worst = max(max(c["ratio"].values()) for c in res) if res else None
    return {"campaigns": res, "worst_ratio": worst, "target": 1.05, "runtime_s": time.perf_counter() - t0}
