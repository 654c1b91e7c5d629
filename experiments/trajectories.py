"""The integrated method on trajectory families it was not tuned on, judged on the continuation of the path.

For each family of :data:`torchcal.sim.PATHS` and seed: a simulated UR5 trajectory with a smooth field, the first
``train_samples`` for calibration, the rest (the path's continuation, a separate file for a user) for the test.
Compared on the continuation: geometry alone (``kinematic``) and ``integrated`` with the engine chosen on
validation (``engine="auto"``), or any other engine asked for.
"""

from __future__ import annotations

import time

import torch

from torchcal._threads import torch_threads
from torchcal.data import Measurements, read_measurements
from torchcal.effects import Context
from torchcal.effects.region import coverage, predictive_sigma
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.stats import rmse


def _residuals(model, test: Measurements):
    """Prediction minus measurement per tracker axis ``(N, 3)`` [m]."""
    with torch.no_grad():
        return model(Context.from_measurements(test, trajectory=True)) - test.p


def continuation_rmse_mm(model, test: Measurements) -> float:
    """RMSE on the continuation ``test`` [mm] of a model (predict's prediction)."""
    return rmse(errors(model, test, trajectory=True)) * 1e3


def compare(train: Measurements, test: Measurements, robot: str = "ur5", engines=("auto",), seed: int = 0) -> dict:
    """Geometry alone and the integrated method (each engine) on one campaign, on its continuation."""
    out = {}
    t0 = time.perf_counter()
    kin = calibrate(robot, train, Options(method="kinematic", seed=seed, refit=True))
    out["kinematic"] = {
        "continuation_rmse_mm": continuation_rmse_mm(kin.model, test),
        "seconds": time.perf_counter() - t0,
    }
    for engine in engines:
        t0 = time.perf_counter()
        run = calibrate(robot, train, Options.of(method="integrated", engine=engine, seed=seed))
        sel = next(
            (r.evidence.get("selection") for r in list(run.effects) + list(run.rejections) if r.name == "integrated"),
            None,
        )
        seconds = time.perf_counter() - t0
        sigma = predictive_sigma(run.model, test.q)
        ev = run.effects[-1].evidence.get("predictive_sigma", {}) if run.effects else {}
        out[f"integrated_{engine}"] = {
            "continuation_rmse_mm": continuation_rmse_mm(run.model, test),
            "internal_holdout_mm": run.stages[-1].rmse * 1e3,
            "chosen": (sel or {}).get("chosen") if run.effects else "geometry alone",
            "gate_length": run.effects[-1].params.get("support_gate_length") if run.effects else None,
            # the predicted 2-sigma coverage on the continuation (None where the model has no sigma)
            "coverage_2sigma_continuation": None if sigma is None else coverage(_residuals(run.model, test), sigma),
            "coverage_2sigma_validation": ev.get("coverage_2sigma_validation"),
            "coverage_2sigma_holdout": ev.get("coverage_2sigma_holdout"),
            "seconds": seconds,
        }
    return out


def family_table(
    paths, seeds, field: str = "0.2mm", samples: int = 7342, train_samples: int = 5874, engines=("auto",)
) -> list[dict]:
    """:func:`compare` for every family and seed of simulated trajectories (one torch thread)."""
    rows = []
    with torch_threads(1):
        for path in paths:
            for seed in seeds:
                c = simulate(
                    SimConfig(
                        robot="ur5",
                        trajectory=True,
                        path=path,
                        seed=seed,
                        samples=samples,
                        train_samples=train_samples,
                        effects=[EffectSpec.parse(f"field={field}")],
                    )
                )
                rows.append(
                    {"path": path, "seed": seed, "field": field, **compare(c.train, c.test, engines=engines, seed=0)}
                )
    return rows


def outside_campaign(folder, engines=("auto",)) -> dict:
    """:func:`compare` on an outside trajectory campaign (``train.csv`` and its continuation ``test.csv``)."""
    from pathlib import Path

    folder = Path(folder)
    train = read_measurements(folder / "train.csv", dof=6, require_positions=True)
    test = read_measurements(folder / "test.csv", dof=6, require_positions=True)
    with torch_threads(1):
        return {"campaign": folder.name, **compare(train, test, engines=engines)}
