"""The run directory of a calibration (CONTRACT §4) and reloading it for ``predict``.

Layout::

    report.json            the numbers (CONTRACT §4)
    report.md              the same in words and tables, with the plots below
    *.png                  residual plots
    robot_calibrated.urdf  the calibrated geometry (+ probe and tracker frames)
    model.pt               state_dict of the measurement model (geometry, instrument, lever arm, effects)
    model.json             how to rebuild it: robot description file, effects, options
    robot/<file>           a copy of the robot description the run started from

Everything is written into a temporary directory next to ``out`` and moved into place at the
end, so a failure leaves no partial run directory.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import torch

from torchcal.calibrate import CalibrationRun, rmse
from torchcal.data import Measurements
from torchcal.effects import Context, MeasurementModel, effect_from_config
from torchcal.errors import OptionError
from torchcal.robot import load_robot, resolve_robot_spec

F64 = torch.float64


def _param_table(run: CalibrationRun) -> dict:
    """Estimates with standard deviations, and what was held fixed and why."""
    robot = run.robot
    estimated, fixed = [], []
    fit_by_name = {}
    for f in run.fits:
        std = f.result.std
        for i, name in enumerate(f.result.names):
            fit_by_name[name] = (f.stage, float(std[i]))
    ident_fixed = {}
    for f in run.fits:
        if f.identifiability is not None:
            for d in f.identifiability.fixed:
                ident_fixed[d["name"]] = d["reason"]
    for info in robot.parameter_info():
        grp = robot.groups()[info.group]
        corr = float(grp.delta.detach()[info.index])
        entry = {"name": info.name, "group": info.group, "unit": info.unit, "correction": corr}
        if info.group == "geometry" and hasattr(grp, "values"):
            entry["value"] = float(grp.values.detach()[info.index])
            entry["nominal"] = float(grp.nominal[info.index])
        if info.name in fit_by_name:
            stage, s = fit_by_name[info.name]
            entry["std"] = s
            entry["stage"] = stage
            estimated.append(entry)
        else:
            if info.name in ident_fixed:
                entry["reason"] = ident_fixed[info.name]
            elif not bool(grp.mask[info.index]):
                entry["reason"] = "not a free parameter of this parameterisation (mask)"
            else:
                entry["reason"] = f"not estimated by method '{run.options.method}'"
            fixed.append(entry)
    last = run.fits[-1]
    return {
        "estimated": estimated,
        "fixed": fixed,
        "instrument": {"T_tracker_base": robot.T_tracker_base().detach().tolist()},
        "tool": {"t_flange_probe_m": robot.t_flange_probe().detach().tolist()},
        "largest_correlations": last.result.largest_correlations(10),
        "identifiability": next((f.identifiability.to_dict() for f in reversed(run.fits)
                                 if f.identifiability is not None), None),
        "sigma0_sq": last.result.sigma0_sq,
    }


def _json_safe(x):
    """Plain JSON: non-finite floats become None (``json`` would write the non-standard ``Infinity``)."""
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, torch.Tensor):
        return _json_safe(x.tolist())
    return x


def build_report(run: CalibrationRun) -> dict:
    st = {s.name: s for s in run.stages}
    final = run.stages[-1]
    last = run.fits[-1]
    # outliers by Baarda's data snooping on the final least-squares fit, per pose (max over x, y, z)
    sr = last.result.standardized_residuals()
    if last.whitening is not None:  # the prior's pseudo-observations follow the poses' residuals: not poses
        sr = sr[: 3 * len(last.whitening)]
    w = sr.reshape(-1, 3).abs().max(dim=-1).values
    outliers = [int(run.data.lines[int(run.train_idx[i])]) for i in torch.nonzero(w > 3.29).flatten()]
    return {
        "robot": run.robot.name,
        "robot_spec": str(run.robot_spec),
        "method": run.options.method,
        "n_train": int(len(run.train_idx)),
        "n_holdout": int(len(run.holdout_idx)),
        "split": {"kind": "last samples (trajectory)" if run.trajectory else "seeded random",
                  "holdout_fraction": run.options.holdout, "seed": run.options.seed},
        "rmse_before_mm": st["nominal"].rmse * 1e3,
        "rmse_geometric_mm": st["geometric"].rmse * 1e3,
        "rmse_after_mm": final.rmse * 1e3,
        "max_before_mm": float(st["nominal"].holdout_errors.max()) * 1e3,
        "max_after_mm": float(final.holdout_errors.max()) * 1e3,
        "rmse_train_after_mm": rmse(final.train_errors) * 1e3,
        "global_test": {k: last.global_test[k] for k in ("statistic", "threshold", "passed", "alpha",
                                                         "redundancy")},
        "stochastic_model": {
            "tracker_sigma_m": "per point (sx, sy, sz)" if run.data.sigma is not None else run.options.sigma_tracker,
            "joint_sigma_rad": run.options.sigma_joint,
        },
        "outliers": {"test": "Baarda data snooping |w| > 3.29 on the final least-squares fit", "lines": outliers},
        "effects": _json_safe(run.effects_report),
        "rejected": _json_safe(run.rejected),
        "diagnosis": _json_safe(run.diagnosis.to_dict()) if run.diagnosis is not None else None,
        # structure the final model leaves (CONTRACT §4; empty when the global test passes or no loop ran)
        "unexplained": _json_safe(getattr(run.diagnosis, "unexplained", None) or []),
        "parameters": _param_table(run),
        "stages": [{"name": s.name, "rmse_holdout_mm": s.rmse * 1e3, "rmse_train_mm": rmse(s.train_errors) * 1e3}
                   for s in run.stages],
        "fits": [{"stage": f.stage, "status": f.result.status, "iterations": f.result.iterations,
                  "cost_history": f.result.cost_history, "n_parameters": len(f.result.x),
                  "global_test": f.global_test} for f in run.fits],
        "notes": run.notes,
    }


def write_run(run: CalibrationRun, out: str | os.PathLike) -> Path:
    """Write the run directory (module docstring), all or nothing."""
    from torchcal.report.markdown import write_markdown
    from torchcal.robot.export import write_urdf

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        report = build_report(run)
        (tmp / "report.json").write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
        write_markdown(run, report, tmp)
        write_urdf(run.robot, tmp / "robot_calibrated.urdf")
        src = resolve_robot_spec(run.robot_spec)
        (tmp / "robot").mkdir()
        shutil.copy2(src, tmp / "robot" / src.name)
        torch.save(run.model.state_dict(), tmp / "model.pt")
        meta = {
            "format": "torchcal-run-1",
            "robot_file": f"robot/{src.name}",
            "base_link": run.robot.base_link if run.robot.kind == "urdf" else None,
            "tip_link": run.robot.tip_link if run.robot.kind == "urdf" else None,
            "trajectory": run.trajectory,
            "effects": [{"class": type(e).__name__, **e.config()} for e in run.model.effects],
            "method": run.options.method,
        }
        (tmp / "model.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
        if out.exists():
            old = out.with_name(f".{out.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            out.rename(old)
            tmp.rename(out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def load_model(run_dir: str | os.PathLike) -> tuple[MeasurementModel, dict]:
    """Rebuild the calibrated measurement model of a run directory."""
    run_dir = Path(run_dir)
    meta_path = run_dir / "model.json"
    if not meta_path.is_file():
        raise OptionError(f"{run_dir}: not a torchcal run directory (no model.json)")
    meta = json.loads(meta_path.read_text(encoding="utf-8"))
    robot = load_robot(run_dir / meta["robot_file"], base_link=meta.get("base_link"), tip_link=meta.get("tip_link"))
    model = MeasurementModel(robot, [effect_from_config(c) for c in meta["effects"]])
    model.load_state_dict(torch.load(run_dir / "model.pt", weights_only=True))
    return model, meta


def predict(run_dir: str | os.PathLike, data: Measurements) -> torch.Tensor:
    """Predicted probe positions in the tracker frame ``(N, 3)`` [m] with everything the run learned."""
    model, meta = load_model(run_dir)
    if data.dof != model.robot.dof:
        raise OptionError(f"data have {data.dof} joints but the run's robot '{model.robot.name}' has {model.robot.dof}")
    with torch.no_grad():
        return model(Context.from_measurements(data, trajectory=bool(meta.get("trajectory")) and data.t is not None))
