"""A run's own export used as ``--robot`` for a new calibration (issue 46 item 3): is the new run's sigma honest?

For each campaign (a folder with ``train.csv`` and ``test.csv``), the training rows are calibrated (``method``, the
default by default) and the run's export (``dh``, ``urdf``; the stand-alone geometry ``export`` writes) is loaded as
``--robot`` for a second calibration of the same training rows with the same method, as a user who keeps the
calibrated file and calibrates again would (a URDF to its flange, as ``--robot`` loads a torchcal URDF). Both runs
predict the test rows as ``predict`` does (:func:`torchcal.use.rundir.row_trust`): their RMSE, the share of rows
whose three ``|error| / sigma`` are all <= 3 (target >= 95 %) and the median ``|error| / sigma`` over the axes
(target 0.4-1.0).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import torch

from torchcal.data import Measurements, read_measurements
from torchcal.effects import Context
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.robot.load import calibrated_flange
from torchcal.stats import rmse
from torchcal.use.export import export_run
from torchcal.use.rundir import load_model, row_trust

MM = 1e3
SEED = 0
HOLDOUT = 0.2


def judged(run_dir: Path, test: Measurements) -> dict:
    """The run's RMSE [mm] on ``test`` and its sigma's coverage and median ``|error| / sigma`` there."""
    model, meta = load_model(run_dir)
    ctx = Context.from_measurements(test, trajectory=False)
    sigma = row_trust(run_dir, model, meta, ctx).sigma
    with torch.no_grad():
        e = (model(ctx) - test.p).cpu()
    z = e.abs() / sigma
    return {
        "rmse_mm": rmse(e.norm(dim=1)) * MM,
        "within_3sigma": float((z <= 3.0).all(dim=1).double().mean()),
        "median_ratio": float(z.median()),
        "median_sigma_mm": float(sigma.norm(dim=1).median()) * MM,
        "trust_scale": (meta.get("trust") or {}).get("scale"),
        "effects": [e.get("class") for e in meta.get("effects", [])],
    }


def campaign(folder: Path, robot: str, method: str, formats: tuple[str, ...], tmp: Path) -> dict:
    """One campaign (module docstring)."""
    train, test = read_measurements(folder / "train.csv"), read_measurements(folder / "test.csv")
    opts = Options.of(method=method, seed=SEED, holdout=HOLDOUT, trajectory=False)
    first = write_run(calibrate(robot, train, opts), tmp / f"{folder.name}_first")
    out = {"campaign": folder.name, "method": method, "first": judged(first, test), "again": {}}
    for fmt in formats:
        f = tmp / f"{folder.name}_export.{'yaml' if fmt == 'dh' else 'urdf'}"
        export_run(first, fmt, f)
        again = calibrate(str(f), train, opts, tip_link=calibrated_flange(f) if fmt == "urdf" else None)
        out["again"][fmt] = judged(write_run(again, tmp / f"{folder.name}_{fmt}"), test)
    return out


def run(folders: list[Path], robot: str = "ur5", method: str = "auto", formats: tuple[str, ...] = ("dh",)) -> dict:
    """Every campaign of ``folders`` on ``robot``; the targets over every re-calibration."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        res = [campaign(f, robot, method, formats, Path(tmp)) for f in folders]
    again = [a for c in res for a in c["again"].values()]
    return {
        "campaigns": res,
        "targets": {
            "within 3 sigma >= 95 %": all(a["within_3sigma"] >= 0.95 for a in again),
            "median |e|/sigma 0.4-1.0": all(0.4 <= a["median_ratio"] <= 1.0 for a in again),
        },
        "runtime_s": time.perf_counter() - t0,
    }
