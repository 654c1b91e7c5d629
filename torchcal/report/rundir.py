"""Writing a calibration's run directory (files and report fields are an outside contract; :mod:`torchcal.use.rundir`
reloads it).

Layout::

    .torchcal-run          marker: a torchcal output directory, safe to replace
    report.json            the numbers
    report.md              the same in words and tables, with the plots below
    *.png                  residual plots
    robot_calibrated.urdf  the calibrated geometry (+ probe and tracker frames)
    model.pt               state_dict of the measurement model (geometry, instrument, lever arm, effects)
    model.json             how to rebuild it: robot description file, effects, options, calibrated region
    covariance.pt          the parameter covariance of the last fit (predict's and compensate's sx, sy, sz)
    geometric.pt           a run with effects: its kinematic calibration (beside covariance_geometric.pt), which
                           predicts rows beyond the region where its sigma is far the smaller (model.json: trust)
    standalone.pt          a run with effects: the geometry its exports carry, the one that predicts best without
                           them (torchcal.pipeline.standalone; model.json: standalone)
    holdout.pt             the held-out rows' joints and positions (check-export measures a file on them)
    nominal.pt             the nominal geometry with the fitted instrument pose and lever arm (the run's first stage,
                           beside covariance_nominal.pt), a candidate for the rows beyond the region (model.json:
                           beyond, torchcal.pipeline.beyond); covariance_beyond.pt: where the run's own model
                           predicts there, its covariance bounded by the tolerance priors (the sigma beyond)
    robot/<file>           a copy of the robot description the run started from

Everything is written into a temporary directory next to ``out`` and moved into place at the
end, so a failure leaves no partial run directory; ``out`` is replaced only when it is absent
or an earlier torchcal output (it carries the marker ``.torchcal-run``, see
:mod:`torchcal._outdir`).
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import torch

from torchcal._inputs import read_bounded
from torchcal._outdir import replace_dir
from torchcal.effects import Context, MeasurementModel
from torchcal.errors import EstimationError, TorchcalError
from torchcal.pipeline import CalibrationRun
from torchcal.robot import resolve_robot_spec
from torchcal.robot.load import MAX_DESCRIPTION_BYTES
from torchcal.stats import rmse
from torchcal.use.conditions import training_load

F64 = torch.float64
Tensor = torch.Tensor


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
        if info.name in fit_by_name and info.name not in ident_fixed:  # held after an earlier fit estimated it
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
        "identifiability": next(
            (f.identifiability.to_dict() for f in reversed(run.fits) if f.identifiability is not None), None
        ),
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


#: where a run uses a 6-D probe's orientation (report.json ``orientation.fitted_in``)
ORIENTATION_SCOPE = (
    "the least-squares fits: the nominal start, the kinematic calibration and the closed loop's joint refits (joint "
    "effects turn the probe frame too); the learned corrections and the integrated filter are position-only"
)


def _orientation_report(run: CalibrationRun) -> dict | None:
    """report.json's ``orientation`` (only where the data carry a 6-D probe's orientation): the held-out angle
    between predicted and measured probe orientation per stage (RMS and max, degrees), the stochastic model, the probe
    frame's rotation in the flange, and the parameters the orientation rows make estimable."""
    from torchcal.estimate.fit import SIGMA_ORIENTATION, orientation_errors

    if run.data.r is None or not run.model.robot.has_orientation:
        return None
    stages = []
    for s in run.stages:
        e = orientation_errors(s.model, run.hold, run.trajectory)
        if e is None or not len(e):
            continue
        stages.append(
            {"name": s.name, "rms_holdout_deg": math.degrees(rmse(e)), "max_holdout_deg": math.degrees(float(e.max()))}
        )
    if not stages:  # every held-out row's orientation left out as a gross error
        return None
    by = {s["name"]: s for s in stages}
    final = stages[-1]
    only = next((f.orientation_only for f in run.fits if f.identifiability is not None and f.n_orientation), [])
    rot = run.model.robot.tool_rotation
    return {
        "rms_before_deg": by["nominal"]["rms_holdout_deg"] if "nominal" in by else None,
        "rms_geometric_deg": by["geometric"]["rms_holdout_deg"] if "geometric" in by else None,
        "rms_after_deg": final["rms_holdout_deg"],
        "max_after_deg": final["max_holdout_deg"],
        "stages": stages,
        "sigma_rad": "per row (srx, sry, srz)"
        if run.data.sigma_r is not None
        else (run.options.fit.sigma_orientation or SIGMA_ORIENTATION),
        "rows_fitted": max((f.n_orientation for f in run.fits), default=0),
        # the factor the orientation sigmas were scaled by: the positions' variance factor, times the lead (fit.py)
        "sigma_scale": next((f.orientation_scale for f in reversed(run.fits) if f.n_orientation), 1.0),
        "fitted_in": ORIENTATION_SCOPE,
        "R_flange_probe": rot.matrix().detach().tolist(),
        "estimable_only_with_orientation": list(only),
    }


def build_report(run: CalibrationRun, train_ctx: Context | None = None) -> dict:
    """report.json's fields; ``train_ctx``: the context of the training rows where the caller has one (the run
    directory's writer evaluates the model there again: the learned corrections keep their last evaluation)."""
    st = {s.name: s for s in run.stages}
    final = run.stages[-1]
    last = run.fits[-1]
    # gross errors: the robust screening's rejected rows, training and held-out (torchcal.estimate.robust)
    screening = getattr(run, "screening", None)
    outliers = (
        screening.to_dict()
        if screening is not None
        else {"method": "none (screening switched off)", "training": None, "holdout": None, "lines": []}
    )
    return {
        "robot": run.robot.name,
        "robot_spec": str(run.robot_spec),
        "method": run.options.method,
        "device": run.options.device,
        "n_train": int(len(run.train_idx)),
        "n_holdout": int(len(run.holdout_idx)),
        "split": {
            "kind": "last samples (trajectory)" if run.trajectory else "seeded random",
            "holdout_fraction": run.options.split.holdout,
            "seed": run.options.seed,
            **(run.split.to_dict() if run.split is not None else {}),
        },
        "rmse_before_mm": st["nominal"].rmse * 1e3,
        "rmse_geometric_mm": st["geometric"].rmse * 1e3,
        "rmse_after_mm": final.rmse * 1e3,
        "max_before_mm": float(st["nominal"].holdout_errors.max()) * 1e3,
        "max_after_mm": float(final.holdout_errors.max()) * 1e3,
        "rmse_train_after_mm": rmse(final.train_errors) * 1e3,
        "global_test": {
            **{k: last.global_test[k] for k in ("statistic", "threshold", "passed", "alpha", "redundancy")},
            **_json_safe(_global_test_reading(run, train_ctx)),
        },
        "stochastic_model": {
            "tracker_sigma_m": "per point (sx, sy, sz)"
            if run.data.sigma is not None
            else run.options.fit.sigma_tracker,
            "joint_sigma_rad": run.options.fit.sigma_joint,
        },
        "outliers": _json_safe(outliers),
        "effects": _json_safe(run.effects_report + _carried_effects(run)),
        "rejected": _json_safe(run.rejected),
        "diagnosis": _json_safe(run.diagnosis.to_dict()) if run.diagnosis is not None else None,
        # structure the final model leaves (CONTRACT §4; empty when the global test passes or no loop ran): the loop
        # lists it when its last fit fails the test, and a later stage (the learned model, the held-out guard's
        # choice) can pass it, so the report's own global test decides, and report.md says the same
        "unexplained": []
        if last.global_test.get("passed", True)
        else _json_safe(getattr(run.diagnosis, "unexplained", None) or []),
        # the auto method: the final model against the kinematic calibration on the held-out poses (None otherwise)
        "holdout_guard": _json_safe(getattr(run, "holdout_guard", None)),
        "parameters": _param_table(run),
        "stages": [
            {"name": s.name, "rmse_holdout_mm": s.rmse * 1e3, "rmse_train_mm": rmse(s.train_errors) * 1e3}
            for s in run.stages
        ],
        "fits": [
            {
                "stage": f.stage,
                "status": f.result.status,
                "iterations": f.result.iterations,
                "cost_history": f.result.cost_history,
                "n_parameters": len(f.result.x),
                "global_test": f.global_test,
            }
            for f in run.fits
        ],
        "notes": run.notes,
        "region": _region_report(run.model, run),
        # a calibration from a prior run: each parameter's change in its prior sigmas, the ones that moved
        **({"prior": _json_safe(run.prior_update.to_dict())} if run.prior_update is not None else {}),
        # a 6-D probe's orientation (held-out errors in degrees per stage); absent for position-only data
        **({"orientation": _json_safe(o)} if (o := _orientation_report(run)) is not None else {}),
        **_stations_report(run),
    }


def _global_test_reading(run: CalibrationRun, ctx: Context | None = None) -> dict:
    """What the last fit's global test found (:func:`torchcal.diagnose.noise.global_test_reading`): the instrument's
    noise level from the final model's training residuals, what the model leaves in it, and how to read a failure."""
    from torchcal.diagnose.noise import global_test_reading, noise_level

    train = run.data.subset(run.train_idx)
    if ctx is None:
        ctx = Context.from_measurements(train, trajectory=run.trajectory)
    with torch.no_grad():
        r = train.p - run.model(ctx)
        reach = float(run.model.robot.probe_in_base(train.q).norm(dim=-1).max())
    noise = noise_level(train.q, r, train.sigma, run.options.fit.sigma_tracker)
    st = {s.name: s for s in run.stages}
    return global_test_reading(run.fits[-1].global_test, noise, run.stages[-1].rmse, st["geometric"].rmse, reach)


def _stations_report(run: CalibrationRun) -> dict:
    """report.json's ``stations`` (each instrument placement's pose, its parameters' standard deviations, its
    held-out RMSE and rows) and ``probes`` (each lever arm with its standard deviations), for a run of several; empty
    for one station and one probe."""
    robot = run.robot
    if not robot.stations and not robot.probes:
        return {}
    std = {e["name"]: e.get("std") for e in _param_table(run)["estimated"]}
    final = run.stages[-1]
    out: dict = {}
    if robot.stations:
        hold_st = run.hold.station.cpu()
        train_st = run.train.station.cpu()
        errs = final.holdout_errors.cpu()
        out["stations"] = {}
        for k, name in enumerate(robot.stations):
            e = errs[hold_st == k]
            out["stations"][name] = {
                "T_tracker_base": robot.T_tracker_base(k).detach().cpu().tolist(),
                "std": {c: std.get(f"instrument[{name}].{c}") for c in robot.instrument.COLUMNS},
                "rmse_holdout_mm": rmse(e) * 1e3 if len(e) else None,
                "n_train": int((train_st == k).sum()),
                "n_holdout": int(len(e)),
            }
    if robot.probes:
        out["probes"] = {
            name: {
                "t_flange_probe_m": robot.t_flange_probe(k).detach().cpu().tolist(),
                "std_m": {c: std.get(f"tool[{name}].{c}") for c in robot.tool.COLUMNS},
            }
            for k, name in enumerate(robot.probes)
        }
    return _json_safe(out)


def write_run_files(run: CalibrationRun, directory: str | os.PathLike) -> Path:
    """Write the run's files (module docstring) into the existing empty ``directory``."""
    from torchcal.report.markdown import write_markdown
    from torchcal.robot.export import write_urdf

    tmp = Path(directory)
    state = {k: v.cpu() for k, v in run.model.state_dict().items()}  # written from CPU copies, loads anywhere
    # joint limits may be infinite (continuous joints); every estimated value must be finite
    bad = [
        k
        for k, v in state.items()
        if v.is_floating_point() and not k.endswith("limits") and not bool(torch.isfinite(v).all())
    ]
    if bad:
        raise EstimationError(
            f"the calibrated model has non-finite values in {', '.join(bad[:5])}; the fit diverged, nothing was written"
        )
    # one context of the training rows for every evaluation of the final model there (report.json's global test
    # reading, the URDF's gap and check): its learned corrections keep their last evaluation
    ctx = Context.from_measurements(run.data.subset(run.train_idx), trajectory=run.trajectory)
    report = build_report(run, ctx)
    from torchcal.pipeline.trust import run_trust

    rtrust = run_trust(run)  # predict's sx, sy, sz: measured on the held-out rows (torchcal.estimate.trust)
    report["trust"] = _trust_report(rtrust, int(run.holdout_idx.numel()))
    # the URDF carries the geometry only: say what it leaves out and what that costs on the training poses
    from torchcal.report.urdf import urdf_fk_difference, urdf_gap, urdf_markdown, urdf_notes

    write_urdf(run.robot, tmp / "robot_calibrated.urdf", notes=urdf_notes(urdf_gap(run.model, ctx)))
    report["urdf"] = {
        "file": "robot_calibrated.urdf",
        **urdf_fk_difference(tmp / "robot_calibrated.urdf", run.model, ctx),
    }
    text = json.dumps(_json_safe(report), indent=1, allow_nan=False)
    (tmp / "report.json").write_text(text + "\n", encoding="utf-8")
    write_markdown(run, report, tmp)
    with open(tmp / "report.md", "a", encoding="utf-8") as f:
        f.write(urdf_markdown(report["urdf"]))
    src = resolve_robot_spec(run.robot_spec)
    (tmp / "robot").mkdir()
    # read again after the fit, bounded: the file may have been replaced by a FIFO or a huge file meanwhile
    robot_copy = tmp / "robot" / src.name
    robot_copy.write_bytes(
        read_bounded(src, "robot description", lambda m: TorchcalError(f"{src}: {m}"), limit=MAX_DESCRIPTION_BYTES)
    )
    shutil.copystat(src, robot_copy)
    torch.save(state, tmp / "model.pt")
    if run.covariance is not None:  # predict's sx, sy, sz (absent: a fit without one; predict says so)
        torch.save(run.covariance.state(), tmp / "covariance.pt")
    _write_geometric(rtrust, tmp)
    _write_nominal(rtrust, tmp)
    alone = _write_standalone(run, tmp)
    meta = {
        "format": "torchcal-run-1",
        "robot_file": f"robot/{src.name}",
        "base_link": run.robot.base_link if run.robot.kind == "urdf" else None,
        "tip_link": run.robot.tip_link if run.robot.kind == "urdf" else None,
        "trajectory": run.trajectory,
        "effects": [{"class": type(e).__name__, **e.config()} for e in run.model.effects],
        "method": run.options.method,
        "region": _region_config(run.model),
        "tool_axis": _tool_axis_config(run),
        "load": training_load(run.data),  # the load conditions the run was fitted in (torchcal.use.conditions)
        "trust": None if rtrust.full is None else rtrust.full.to_dict(),
        **({"trust_few_rows": rtrust.few.to_dict()} if rtrust.few is not None else {}),
        **({"geometric": {"trust": rtrust.geometric.to_dict()}} if rtrust.geometric is not None else {}),
        **_beyond_config(rtrust),
        **({"standalone": alone} if alone is not None else {}),
        **({"stations": list(run.robot.stations)} if run.robot.stations else {}),
        **({"probes": list(run.robot.probes)} if run.robot.probes else {}),
        **_single_labels(run),
    }
    (tmp / "model.json").write_text(json.dumps(meta, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    return tmp


def _carried_effects(run) -> list[dict]:
    """A calibration from a prior run: the prior's effects, which its model carries as they were fitted, each marked
    ``carried_from_prior`` (they were not found or refitted on these rows)."""
    prior = getattr(run, "prior", None)
    if prior is None:
        return []
    return [{**e, "carried_from_prior": prior.source} for e in prior.effects]


def _single_labels(run) -> dict:
    """``model.json``'s ``labels``: the one station (probe) name of the rows, where the data name one and the robot
    has a single instrument pose (lever arm). The run then knows which placement and probe it was fitted for, and
    ``predict`` and ``compensate`` refuse rows that name another (:func:`torchcal.use.rundir.check_placement`)
    instead of predicting them in this one's frame."""
    labels = {}
    for key, known in (("station", run.robot.stations), ("probe", run.robot.probes)):
        index, names = getattr(run.data, key), getattr(run.data, f"{key}_names")
        if known or index is None:
            continue
        used = sorted({names[int(i)] for i in torch.unique(index.cpu())})
        if len(used) == 1:
            labels[key] = used[0]
    return {"labels": labels} if labels else {}


def _trust_report(rt, n_holdout: int) -> dict:
    """report.json's ``trust``: what the predictive sigma adds to the parameters (:mod:`torchcal.estimate.trust`),
    measured on the held-out rows, of the final model and of the kinematic calibration beside it; where too few rows
    were held out to measure it, a note that says what predict's sigma then lacks."""
    from torchcal.estimate.trust import MIN_ROWS

    out = {
        "definition": "sx, sy, sz: the standard deviation of a new measurement minus the prediction (docs/trust.md)",
        "model": None if rt.full is None else rt.full.to_dict(),
    }
    if rt.full is None and rt.few is not None:
        out["few_rows"] = rt.few.to_dict()
        out["note"] = rt.few.note()
    elif rt.full is None and n_holdout < MIN_ROWS:
        out["note"] = (
            f"not measured: {n_holdout} held-out rows, fewer than {MIN_ROWS}; predict's sx, sy, sz hold the "
            "parameters' and the learned model's uncertainty only and understate the error (judge the run on a "
            "separate check file)"
        )
    if rt.geometric is not None:
        out["geometric"] = rt.geometric.to_dict()
    for name in ("nominal", "physical"):
        if getattr(rt, name) is not None:
            out[name] = getattr(rt, name).to_dict()
    if rt.choice is not None:
        out["beyond"] = rt.choice.to_dict()
    return out


def _write_geometric(rt, tmp: Path) -> None:
    """``geometric.pt`` (and ``covariance_geometric.pt``): the kinematic calibration beside a final model that is not
    it, the model predict and compensate use beyond the region where its sigma is far the smaller."""
    if rt.geometric_model is None or rt.geometric is None:
        return
    torch.save({k: v.cpu() for k, v in rt.geometric_model.state_dict().items()}, tmp / "geometric.pt")
    if rt.geometric_covariance is not None:
        torch.save(rt.geometric_covariance.state(), tmp / "covariance_geometric.pt")


def _write_nominal(rt, tmp: Path) -> None:
    """``nominal.pt`` (and ``covariance_nominal.pt``): the nominal geometry with the fitted instrument pose and lever
    arm, a candidate for the rows beyond the region (:mod:`torchcal.pipeline.beyond`)."""
    if rt.nominal_model is None or rt.nominal is None:
        return
    torch.save({k: v.cpu() for k, v in rt.nominal_model.state_dict().items()}, tmp / "nominal.pt")
    if rt.nominal_covariance is not None:
        torch.save(rt.nominal_covariance.state(), tmp / "covariance_nominal.pt")
    if rt.beyond_covariance is not None and rt.beyond is not None:
        torch.save(rt.beyond_covariance.state(), tmp / "covariance_beyond.pt")


def _beyond_config(rt) -> dict:
    """model.json's ``nominal`` and ``physical`` (each candidate's measured sigma) and ``beyond`` (which candidate
    predicts the rows beyond the region, and on what evidence)."""
    out = {}
    if rt.nominal_model is not None and rt.nominal is not None:
        out["nominal"] = {"trust": rt.nominal.to_dict()}
    if rt.physical is not None:
        out["physical"] = {"trust": rt.physical.to_dict()}
    if rt.choice is not None:
        out["beyond"] = rt.choice.to_dict()
        if rt.beyond is not None:
            out["beyond"]["trust"] = rt.beyond.to_dict()
    return out


def _write_standalone(run: CalibrationRun, tmp: Path) -> dict | None:
    """``holdout.pt`` (the held-out rows' joints, positions, station and probe: what ``check-export`` measures a file
    on) and, for a model with effects, ``standalone.pt``: the geometry its exports carry
    (:mod:`torchcal.pipeline.standalone`). Returns model.json's ``standalone`` (None without one)."""
    from torchcal.pipeline.standalone import standalone

    hold = run.hold.to("cpu")
    if hold.p is None or hold.n == 0:
        return None
    rows = {"q": hold.q, "p": hold.p}
    rows.update({k: getattr(hold, k) for k in ("station", "probe") if getattr(hold, k) is not None})
    torch.save(rows, tmp / "holdout.pt")
    alone = standalone(run)
    if alone is None:
        return None
    torch.save({k: v.cpu() for k, v in alone.model.state_dict().items()}, tmp / "standalone.pt")
    return alone.to_dict()


def _region_report(model: MeasurementModel, run: CalibrationRun | None = None) -> dict | None:
    """report.json's ``region``: model.json's (:func:`_region_config`), the fade length, the fitted range of each
    open joint form (by ``kind:joint``) and the time region a drift in time holds beyond (its key
    ``drift_time_span`` as report.json has always written it)."""
    from torchcal.effects.joint import FADE_LENGTH, RegionForm

    cfg = _region_config(model)
    if cfg is None:
        return None
    forms = {
        f"{e.kind}:{e.joint}": [float(v) for v in e.region]
        for e in model.effects
        if isinstance(e, RegionForm) and e.region is not None
    }
    times = [[float(v) for v in e.region] for e in model.effects if e.kind == "drift" and e.region is not None]
    return {
        "joint_min": cfg["joint_min"],
        "joint_max": cfg["joint_max"],
        "learned_fade": cfg["fade"],
        "fade_length": FADE_LENGTH,
        "open_forms": forms,
        # a drift in time holds its value beyond the times it was fitted on [s] (every drift in t is fitted on one)
        "drift_time_span": times[0] if times else None,
        # the joints the training poses hardly moved (torchcal.pipeline.checks.narrow_joints)
        **({"narrow_joints": _narrow_report(run)} if run is not None else {}),
    }


def _tool_axis_config(run: CalibrationRun) -> dict | None:
    """model.json's ``tool_axis``: the cone of the flange's z axis (the tool axis) in the base frame over the training
    rows, as its mean direction and the largest angle of a row from it [rad]; predict and compensate flag rows beyond
    it (a tool turned over, which joint ranges alone do not tell). None where the axes point every way."""
    from torchcal.use.rundir import tool_axis_cone

    with torch.no_grad():
        return tool_axis_cone(run.robot, run.train.q)


def _narrow_report(run: CalibrationRun) -> list[dict]:
    from torchcal.pipeline.checks import narrow_joints

    if run.prior is not None:  # an update's rows: the region is the prior run's (torchcal.pipeline.run.start)
        return []
    robot = run.model.robot
    return [n.to_dict() for n in narrow_joints(run.data.q[run.train_idx], robot.limits, robot.joint_types)]


def _region_config(model: MeasurementModel) -> dict | None:
    """model.json's ``region``: the calibrated range of every joint and whether the learned corrections fade beyond
    it (:meth:`~torchcal.effects.MeasurementModel.set_region`)."""
    if model.region is None:
        return None
    r = model.region.cpu()
    return {"joint_min": r[0].tolist(), "joint_max": r[1].tolist(), "fade": bool(model.region_fade)}


def write_run(run: CalibrationRun, out: str | os.PathLike, *, inputs=()) -> Path:
    """Write the run directory (module docstring), all or nothing.

    ``out`` is replaced only when it is absent or an earlier torchcal run (see
    :mod:`torchcal._outdir`); anything else raises :class:`~torchcal.errors.OptionError`.
    """
    with replace_dir(out, kind="calibrate", inputs=inputs) as tmp:
        write_run_files(run, tmp)
    return Path(out)
