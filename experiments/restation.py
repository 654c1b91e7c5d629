"""Re-stationing on the real UR10: calibrate one series, re-station it on a few points of another (another placement
of the tracker, another tool), and predict that series' held-out poses.

The ipa-robot-accuracy series were measured from different tracker placements and with different tools (README of
the data set). Series ``fit`` (default A) is calibrated (``methods``: kinematic, and the default ``auto`` where
asked) and written as a run directory; for each seed, ``points`` rows drawn at random from the training split of
series ``target`` (default D; calibrate's own grouped held-out split, :func:`torchcal.pipeline.holdout_split`)
re-station it (:func:`torchcal.use.station.fit_station`: the instrument pose and the lever arm, the robot's
calibration held), and the target's held-out poses are predicted. The same re-stationing of the nominal model is the
baseline, the target's own kinematic calibration (on its whole training split) the reference.
"""

from __future__ import annotations

import copy
import tempfile
import time
from pathlib import Path

import torch

from experiments.ipa_series import series_file
from torchcal.data import Measurements, read_ipa
from torchcal.effects import MeasurementModel
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate, holdout_split
from torchcal.report.rundir import write_run
from torchcal.robot import load_robot
from torchcal.sweep import map_tasks
from torchcal.use.rundir import load_covariance, load_model
from torchcal.use.station import fit_station, one_placement, station_options

ROBOT = "ur10"
SEED = 0
HOLDOUT = 0.2
MM = 1e3


def _rmse(e: torch.Tensor) -> float:
    return float(e.square().mean().sqrt()) * MM


def _summary(values: list[float]) -> dict:
    v = sorted(values)
    return {
        "median": v[len(v) // 2] if len(v) % 2 else 0.5 * (v[len(v) // 2 - 1] + v[len(v) // 2]),
        "min": v[0],
        "max": v[-1],
        "values": values,
    }


def _restation(model: MeasurementModel, cov, pts: Measurements, held: Measurements, opts) -> dict:
    model = copy.deepcopy(model)
    st = fit_station(model, pts, opts, cov)
    d = st.to_dict()
    return {
        "rmse_mm": _rmse(errors(model, held, trajectory=False)),
        "points_rmse_mm": d["rmse_points_mm"],
        "placement_sigma_rms_mm": d["accuracy"]["placement_sigma_rms_mm"],
        "predicted_rmse_mm": d["accuracy"]["predicted_rmse_mm"],
        "chi_square_passed": d["chi_square"]["passed"],
        "lever_mm": [float(v) * MM for v in st.t_flange_probe],
        "warnings": len(st.warnings),
    }


def _restation_task(task: tuple) -> dict:
    """One re-stationing ``(model, cov, pts, held, opts)``: a task of :func:`torchcal.sweep.map_tasks`."""
    return _restation(*task)


def run(
    data_dir: Path,
    fit: str = "A",
    target: str = "D",
    points: int = 6,
    seeds: int = 5,
    methods: tuple[str, ...] = ("kinematic",),
    tool: bool = True,
    workers: int | None = None,
    address: str | None = None,
) -> dict:
    """The experiment (module docstring); the re-stationings, independent fits, on ``workers`` Ray CPUs or the
    cluster at ``address`` (:func:`torchcal.sweep.map_tasks`; default one after another, the same results)."""
    t0 = time.perf_counter()
    src = read_ipa(series_file(data_dir, fit))
    dst = read_ipa(series_file(data_dir, target))
    split = holdout_split(dst, HOLDOUT, SEED, trajectory=False)
    train_idx, held_idx = torch.sort(split.keep).values, torch.sort(split.held).values
    held = dst.subset(held_idx)
    # the reference: the target's own kinematic calibration, its held-out error on the same split
    own = calibrate(ROBOT, dst, Options.of(method="kinematic", seed=SEED, holdout=HOLDOUT, trajectory=False))
    if not torch.equal(torch.sort(own.holdout_idx).values, held_idx):  # the split calibrate makes, or it is a bug
        raise RuntimeError("holdout_split and calibrate disagree on the target's held-out poses")
    out: dict = {
        "fit_series": fit,
        "target_series": target,
        "points": points,
        "seeds": seeds,
        "lever_arm_fitted": tool,
        "n_target_train": int(len(train_idx)),
        "n_target_holdout": int(len(held_idx)),
        "target_own_kinematic_mm": own.stages[-1].rmse * MM,
        "target_own_nominal_mm": {s.name: s for s in own.stages}["nominal"].rmse * MM,
        "methods": {},
    }
    draws = []
    for s in range(seeds):
        g = torch.Generator().manual_seed(s)
        pick = train_idx[torch.randperm(len(train_idx), generator=g)[:points]]
        draws.append(dst.subset(torch.sort(pick).values))
    nominal = MeasurementModel(load_robot(ROBOT))
    # every (model, draw) re-stationing is an independent fit: one sweep over all of them, after the calibrations
    models = {None: (nominal, None, station_options(Path("."), tool=tool))}  # defaults: the nominal's numbers
    with tempfile.TemporaryDirectory() as tmp:
        for method in methods:
            t1 = time.perf_counter()
            run_ = calibrate(ROBOT, src, Options.of(method=method, seed=SEED, holdout=HOLDOUT, trajectory=False))
            cal_s = time.perf_counter() - t1
            rd = write_run(run_, Path(tmp) / method.replace("+", "_"))
            model, meta = load_model(rd)
            # as `torchcal station` does: a learned correction's fallback geometry moves with the instrument
            model, _, cov = one_placement(model, meta, load_covariance(rd, model))
            models[method] = (model, cov, station_options(rd, tool=tool))
            out["methods"][method] = {"fit_series_holdout_mm": run_.stages[-1].rmse * MM, "calibration_s": cal_s}
    tasks = [(model, cov, pts, held, opts) for model, cov, opts in models.values() for pts in draws]
    done = map_tasks(_restation_task, tasks, workers=workers, address=address)
    per_model = {name: done[i * seeds : (i + 1) * seeds] for i, name in enumerate(models)}
    base = per_model.pop(None)
    out["nominal_restationed"] = {"rmse_mm": _summary([b["rmse_mm"] for b in base]), "per_seed": base}
    for method, per in per_model.items():
        rm = _summary([p["rmse_mm"] for p in per])
        out["methods"][method] |= {
            "rmse_mm": rm,
            "ratio_to_own_kinematic": rm["median"] / out["target_own_kinematic_mm"],
            "predicted_rmse_mm": _summary([p["predicted_rmse_mm"] for p in per]),
            "per_seed": per,
        }
    out["runtime_s"] = time.perf_counter() - t0
    return out


def markdown(res: dict) -> str:
    def rng(s: dict) -> str:
        return f"{s['median']:.3f} ({s['min']:.3f}-{s['max']:.3f})"

    lines = [
        f"Re-stationed on {res['points']} points of Series {res['target_series']} (seeds 0..{res['seeds'] - 1}, "
        f"lever arm {'fitted' if res['lever_arm_fitted'] else 'held'}); held-out RMSE [mm] on "
        f"{res['n_target_holdout']} poses, median (range):",
        "",
        "| model | re-stationed | predicted | ratio to the target's own kinematic |",
        "|---|---|---|---|",
        f"| nominal | {rng(res['nominal_restationed']['rmse_mm'])} | - | - |",
    ]
    for m, r in res["methods"].items():
        lines.append(
            f"| Series {res['fit_series']} {m} | {rng(r['rmse_mm'])} | {rng(r['predicted_rmse_mm'])} | "
            f"{r['ratio_to_own_kinematic']:.2f} |"
        )
    lines += [
        "",
        f"Series {res['target_series']}'s own kinematic calibration: {res['target_own_kinematic_mm']:.3f} mm "
        f"(nominal with tracker and lever fitted on all its training poses: {res['target_own_nominal_mm']:.3f}).",
    ]
    return "\n".join(lines) + "\n"
