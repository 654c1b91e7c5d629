"""``calibrate --method integrated`` on simulated continuous trajectories in the paper's setting; prints JSON.

Setting (Horvath & Neuner 2024, Sec. 2.2.1 and 3): a UR5 trajectory of ``--samples`` samples (default 7342, the
paper's count) from torchcal's simulator, the geometry biased (0.1 mm / 0.01 deg per DH parameter), an unknown
tracker pose and lever arm, 15 um tracker and 0.0005 deg joint noise, and a smooth non-geometric field (a
random 6-29-3 tanh network) of ``--field`` RMS at the probe. The whole trajectory is the data file; the
calibration holds out its last 20 % (the test phase) and fits on the rest.

The target this script measures: on such a trajectory, with the field sized so that the kinematic
calibration alone leaves about 0.19 mm on the held-out samples (``--field auto``, the default, sizes it per
seed by one kinematic calibration; on seed 0, 0.26 mm RMS does it, on other seeds it is smaller), the integrated
method should reach 0.10 mm or less. Per seed we report the held-out RMSE of every stage (nominal,
geometric, integrated), the RMSE after each internal step of the method (the network's LM initialisation --
what the sequential kinCalib+ gives --, the joint refinement, the geometry refit, the filter), the filter's
own test-phase prediction, and the oracle (the true model with the same noisy joint readings: the floor).

Measured (``--seeds 0 1 2``, then ``--seeds 3 4``; defaults otherwise; about 90 s per seed on one thread),
held-out RMSE in mm, the kinematic calibration leaving 0.190 on every seed, the oracle 0.027-0.028:

    seed   field RMS   initial network   joint refinement   integrated (final)   filter's own prediction
    0      0.255       0.195             0.182              0.147                0.146
    1      0.160       0.088             0.079              0.068                0.068
    2      0.164       0.182             0.108              0.084                0.085
    3      0.280       0.123             0.174              0.176                0.176
    4      0.272       0.138             0.128              0.112                0.112

The target (<= 0.10 mm) is met on 2 of 5 seeds (mean 0.117 mm); the integrated model beats geometry alone on
all 5, and the network's LM start (what the sequential kinCalib+ gives, mean 0.145 mm) on 4. What limits it:
the held-out samples lie far from the training ones in joint space (median nearest-neighbour distance ~1.3 rad
on seed 0), so the learned part extrapolates, and how well depends on how the geometry and the network share
the field -- the joint refinement moves that share, judged on the last training samples, which on seed 3
picked a state that extrapolates worse.

    python scripts/integrated_trajectory.py [--seeds 0 1 2] [--field auto | 0.26mm] [--samples 7342] [--threads 1]

The last stdout line is one JSON object: {"seeds": {"0": {...}, ...}, "mean": {...}, "config": {...}}.
"""

from __future__ import annotations

import dataclasses
import math
import time

import torch

from torchcal.data import Measurements
from torchcal.effects import Context
from torchcal.pipeline import Options, calibrate
from torchcal.sim import EffectSpec, SimConfig, simulate


def trajectory_data(samples: int, field: str, seed: int):
    """The simulated trajectory as one measurement set (train and test parts of the campaign joined)."""
    c = simulate(
        SimConfig(
            robot="ur5",
            trajectory=True,
            samples=samples,
            train_samples=samples - 1,
            seed=seed,
            effects=[EffectSpec.parse(f"field={field}")],
        )
    )
    parts = (c.train, c.test)
    data = Measurements(
        q=torch.cat([m.q for m in parts]),
        p=torch.cat([m.p for m in parts]),
        t=torch.cat([m.t for m in parts]),
        sigma=torch.cat([m.sigma for m in parts]),
    )
    return c, data


def field_for(samples: int, seed: int, target_mm: float, probe: str = "0.26mm") -> str:
    """The field size at which the kinematic calibration leaves ``target_mm`` on the held-out samples.

    One kinematic calibration with a probe size; the field's share of the held-out error scales with its
    size and adds in quadrature to the noise floor (the oracle's error).
    """
    c, data = trajectory_data(samples, probe, seed)
    run = calibrate("ur5", data, Options(method="kinematic", seed=seed))
    hold = data.subset(run.holdout_idx)
    with torch.no_grad():
        floor = (
            float(
                (c.model(Context.from_measurements(hold, trajectory=True)) - hold.p).norm(dim=-1).square().mean().sqrt()
            )
            * 1e3
        )
    geo = run.stages[-1].rmse * 1e3
    size = float(probe.removesuffix("mm")) * math.sqrt(max(target_mm**2 - floor**2, 0.0) / (geo**2 - floor**2))
    return f"{size:.4f}mm"


def one_seed(
    samples: int,
    field: str,
    seed: int,
    engine: str = "adaptive",
    *,
    run_seed: int | None = None,
    tolerance: bool = True,
) -> dict:
    """One trajectory of seed ``seed`` calibrated with ``engine``; ``run_seed`` is the calibration's own seed (default
    ``seed``; tests/filter/test_integrated.py runs its trajectory of seed 4 with 0), and ``tolerance=False`` fits the
    kinematic calibration under the wide priors instead of the tolerance priors (what the integrated method seeded
    its filter with before issue 51)."""
    t0 = time.perf_counter()
    if field.startswith("auto"):
        field = field_for(samples, seed, float(field.split(":")[1]) if ":" in field else 0.19)
    c, data = trajectory_data(samples, field, seed)
    opts = Options.of(method="integrated", seed=seed if run_seed is None else run_seed, engine=engine)
    if not tolerance:
        opts = dataclasses.replace(opts, fit=dataclasses.replace(opts.fit, tolerance_length=None))
    run = calibrate("ur5", data, opts)
    hold = data.subset(run.holdout_idx)
    with torch.no_grad():
        oracle = (c.model(Context.from_measurements(hold, trajectory=True)) - hold.p).norm(dim=-1)
    ev = run.effects_report[-1]["evidence"]
    return {
        "holdout_rmse_mm": {s.name: s.rmse * 1e3 for s in run.stages},
        "engine": engine,
        "steps_mm": {**ev.get("holdout_rmse_steps_mm", {}), "filter (final model)": run.stages[-1].rmse * 1e3},
        "filter_prediction_mm": ev["holdout_rmse_filter_prediction_mm"],
        "oracle_mm": float(oracle.square().mean().sqrt()) * 1e3,
        "field": field,
        "field_rms_mm": c.truth["effects"][0]["rms_m"] * 1e3,
        "field_variation_mm": c.truth["effects"][0]["variation_m"] * 1e3,
        "nis_mean": ev["filter"]["nis_mean"],
        "n_train": int(len(run.train_idx)),
        "n_holdout": int(len(run.holdout_idx)),
        "seconds": time.perf_counter() - t0,
    }
