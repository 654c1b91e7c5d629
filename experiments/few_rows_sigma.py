"""Sigma from a few held-out rows (issue 46 item 6): small single-station campaigns like those of tests/paths (40
poses, 20 % held out: 8 rows, fewer than a measured level needs), each judged on many fresh test rows.

Per robot (``ur5``, the parallelogram ``fanuc_like`` of tests/robot/data, ``ur10_track``) and seed: ``simulate`` with
a 50 um joint-2 compliance, ``calibrate`` (``method``), and ``predict``'s sigma (:func:`torchcal.use.rundir.row_trust`)
at ``test_poses`` test rows: the share whose three ``|error| / sigma`` are all <= 3 (target >= 95 %) and the median
``|error| / sigma`` over the axes (target >= 0.3), with the few-rows scale the run chose and its bounds.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import torch

from torchcal.effects import Context
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.use.rundir import load_model, row_trust

DATA = Path(__file__).resolve().parents[1] / "tests" / "robot" / "data"
ROBOTS = {"ur5": "ur5", "fanuc_like": str(DATA / "fanuc_like.yaml"), "ur10_track": "ur10_track"}
EFFECT = "compliance:2=50um"


def case(robot: str, seed: int, poses: int, test_poses: int, method: str, tmp: Path) -> dict:
    """One campaign (module docstring)."""
    effects = [EffectSpec.parse(EFFECT)]
    c = simulate(SimConfig(robot=ROBOTS[robot], poses=poses, test_poses=test_poses, seed=seed, effects=effects))
    rd = write_run(calibrate(ROBOTS[robot], c.train, Options.of(method=method, seed=1)), tmp / f"{robot}_{seed}")
    model, meta = load_model(rd)
    ctx = Context.from_measurements(c.test, trajectory=False)
    sigma = row_trust(rd, model, meta, ctx).sigma
    with torch.no_grad():
        e = (model(ctx) - c.test.p).abs().cpu()
    z = e / sigma
    few = meta.get("trust_few_rows") or {}
    return {
        "robot": robot,
        "seed": seed,
        "within_3sigma": float((z <= 3.0).all(dim=1).double().mean()),
        "median_ratio": float(z.median()),
        "rmse_mm": float(e.square().sum(1).mean().sqrt()) * 1e3,
        "max_sigma_mm": float(sigma.max()) * 1e3,
        "n_holdout": few.get("n_holdout", (meta.get("trust") or {}).get("n_holdout")),
        "few_rows_scale": few.get("scale"),
        "few_rows_bounds": few.get("scale_bounds"),
        "effects": [e.get("class") for e in meta.get("effects", [])],
    }


def run(robots=tuple(ROBOTS), seeds=(1, 2, 3, 4), poses: int = 40, test_poses: int = 200, method: str = "auto") -> dict:
    """Every robot and seed; the targets over all of them."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        res = [case(r, s, poses, test_poses, method, Path(tmp)) for r in robots for s in seeds]
    return {
        "cases": res,
        "targets": {
            "within 3 sigma >= 95 %": all(c["within_3sigma"] >= 0.95 for c in res),
            "median |e|/sigma >= 0.3": all(c["median_ratio"] >= 0.3 for c in res),
        },
        "runtime_s": time.perf_counter() - t0,
    }
