"""The real UR10's full 6-D pose (ipa-robot-accuracy: a Leica tracker and a T-Mac; issue 26, item 4): position-only
against full-pose calibration on the same grouped held-out split.

Per series and method, ``calibrate`` runs twice on the same rows with the same seed, hence the same split (it is
drawn from the joints alone): once on the positions alone (the rows' ``r``, ``sigma_r`` dropped) and once on the
full pose (each row's orientation residual whitened by its own covariance: Series B-D's per-axis sigmas, Series A
the default orientation noise, :data:`~torchcal.estimate.fit.SIGMA_ORIENTATION`). Reported on the held-out poses:

* position RMSE / max [mm]: nominal (tracker pose and lever arm fitted), after the geometric fit, final;
* orientation RMSE / max [deg]: the same stages of the full-pose run, and of the position-only run with the probe
  frame's rotation in the flange fitted afterwards in closed form on its training rows
  (:func:`~torchcal.estimate.fit.place_tool_rotation`: the best a position-only calibration can say about
  orientation);
* which parameters the orientation rows make estimable (the geometric fit's analysis with and without them).

Series A (11 911 rows) is subsampled (seeded) with ``--a-rows``; 0 takes every row.
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import torch

from experiments.ipa_series import series_file, subsample
from torchcal.data import Measurements, read_ipa
from torchcal.estimate.fit import errors, orientation_errors, place_tool_rotation
from torchcal.pipeline import Options, calibrate

ROBOT = "ur10"
SERIES = ("A", "B", "C", "D")
METHODS = ("kinematic", "auto")
SEED = 0
MM = 1e3


def _pos(e: torch.Tensor) -> dict:
    return {"rmse_mm": float(e.square().mean().sqrt()) * MM, "max_mm": float(e.max()) * MM}


def _ori(e: torch.Tensor | None) -> dict | None:
    if e is None:
        return None
    return {"rmse_deg": math.degrees(float(e.square().mean().sqrt())), "max_deg": math.degrees(float(e.max()))}


def _stages(run, hold: Measurements, train: Measurements, orientation_fitted: bool) -> dict:
    """Held-out position and orientation errors of the run's nominal, geometric and final stages; a run on the
    positions alone gets the probe frame's rotation fitted afterwards on its training rows (closed form)."""
    out = {}
    for name, stage in (
        ("nominal", run.stage("nominal")),
        ("geometric", run.stage("geometric")),
        ("final", run.stages[-1]),
    ):
        model = stage.model
        if not orientation_fitted:
            model = copy.deepcopy(model)
            place_tool_rotation(model.robot, train.q, train.r)
        out[name] = {
            **_pos(errors(stage.model, hold, run.trajectory)),
            "orientation": _ori(orientation_errors(model, hold, run.trajectory)),
        }
    out["final"]["stage"] = run.stages[-1].name
    return out


def compare(name: str, m: Measurements, method: str) -> dict:
    """Position-only and full-pose calibration of one series with one method (module docstring)."""
    res = {
        "series": name,
        "method": method,
        "n": m.n,
        "orientation_sigma": "per row" if m.sigma_r is not None else "default",
    }
    for label, data in (("position_only", m.without_orientation()), ("full_pose", m)):
        t0 = time.perf_counter()
        run = calibrate(ROBOT, data, Options.of(method=method, seed=SEED, trajectory=False))
        hold, train = m.subset(run.holdout_idx), m.subset(run.train_idx)
        entry = _stages(run, hold, train, data.r is not None)
        entry["seconds"] = time.perf_counter() - t0
        entry["global_test"] = run.fits[-1].global_test["statistic"]
        geo = next((f for f in run.fits if f.identifiability is not None), None)
        if data.r is not None and geo is not None:
            entry["estimable_only_with_orientation"] = list(geo.orientation_only)
        entry["n_train"], entry["n_holdout"] = int(len(run.train_idx)), int(len(run.holdout_idx))
        res[label] = entry
    return res


def run(data_dir: Path, names, methods, a_rows: int) -> dict:
    out = {"robot": ROBOT, "seed": SEED, "results": []}
    for s in names:
        m = read_ipa(series_file(data_dir, s))
        if s == "A":
            m, note = subsample(m, a_rows, SEED)
            if note:
                out["a_rows"] = note
        for method in methods:
            out["results"].append(compare(s, m, method))
    return out


def table(res: dict) -> str:
    """The comparison as a markdown table: held-out position [mm] and orientation [deg], RMSE."""
    lines = [
        "| series | method | position: nominal / position-only / full pose [mm] | "
        "orientation: nominal / position-only / full pose [deg] | orientation-only parameters | time po / fp [s] |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["results"]:
        po, fp = r["position_only"], r["full_pose"]
        lines.append(
            f"| {r['series']} | {r['method']} | {fp['nominal']['rmse_mm']:.3f} / {po['final']['rmse_mm']:.3f} / "
            f"{fp['final']['rmse_mm']:.3f} | {fp['nominal']['orientation']['rmse_deg']:.4f} / "
            f"{po['final']['orientation']['rmse_deg']:.4f} / {fp['final']['orientation']['rmse_deg']:.4f} | "
            f"{', '.join(fp.get('estimable_only_with_orientation') or []) or 'none'} | "
            f"{po['seconds']:.1f} / {fp['seconds']:.1f} |"
        )
    return "\n".join(lines)
