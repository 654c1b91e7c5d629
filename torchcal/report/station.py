"""Writing a re-stationed run: a copy of the calibrated run with the new instrument placement (and lever arm) that
:func:`torchcal.use.station.restation` fitted, and its ``station`` block in ``model.json``, ``report.json`` and
``report.md``."""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
from pathlib import Path

import torch

from torchcal._outdir import MARKER, replace_dir
from torchcal.effects import MeasurementModel
from torchcal.errors import EstimationError
from torchcal.use.station import Station, read_report


def _markdown(station: Station, run_dir: Path, points_file: str) -> str:
    d = station.to_dict()
    acc = d["accuracy"]
    lines = [
        "",
        "## Re-stationed",
        "",
        f"This run is `{run_dir}` with a new instrument placement"
        + (" and lever arm" if station.tool else "")
        + f", fitted to {d['n_points']} points of `{points_file}`; the robot's calibration is unchanged. "
        "The numbers above describe the original calibration at its own placement.",
        "",
        "| parameter | std |",
        "|---|---|",
    ]
    for p in d["parameters"]:
        s = p["std"] * (1e3 if p["unit"] == "m" else 180 / math.pi)
        lines.append(f"| {p['name']} | {s:.4g} {'mm' if p['unit'] == 'm' else 'deg'} |")
    lines += ["", "| line | residual [mm] | leave-one-out [mm] |", "|---|---|---|"]
    for p in d["points"]:
        lo = "-" if p["leave_one_out_mm"] is None else f"{p['leave_one_out_mm']:.4f}"
        lines.append(f"| {p['line']} | {p['residual_mm']:.4f} | {lo} |")
    chi = d["chi_square"]
    lines += [
        "",
        f"Chi-square of the residuals against the run's predicted error: {chi['statistic']:.3g} with {chi['dof']} "
        f"degrees of freedom (threshold {chi['threshold']:.3g} at {chi['alpha']}): "
        f"{'passed' if chi['passed'] else 'not passed'}.",
        "",
        f"Predicted effect on accuracy over {acc['over']}: the placement's position sigma is "
        f"{acc['placement_sigma_rms_mm']:.4f} mm RMS (max {acc['placement_sigma_max_mm']:.4f} mm); with the run's "
        f"model error {acc['run_rmse_mm']:.4f} mm (its sigma over the region, or held-out RMSE) in quadrature, "
        f"{acc['predicted_rmse_mm']:.4f} mm.",
        "",
    ]
    for w in d["warnings"]:
        lines.append(f"- Warning: {w}")
    return "\n".join(lines) + "\n"


#: run files of the old placement that a re-stationed run leaves out
_OLD_PLACEMENT = (
    "geometric.pt",
    "covariance_geometric.pt",
    "standalone.pt",
    "holdout.pt",
    "nominal.pt",
    "covariance_nominal.pt",
    "covariance_beyond.pt",
)


def write_station(
    run_dir: str | os.PathLike,
    model: MeasurementModel,
    meta: dict,
    station: Station,
    out: str | os.PathLike,
    *,
    points_file: str = "points",
    inputs=(),
) -> Path:
    """Write the run ``run_dir`` re-stationed (``model``, ``meta`` and ``station`` as
    :func:`torchcal.use.station.restation` returns them) as a run directory ``out`` (all or nothing, ``out`` replaced
    only when absent or an earlier torchcal output): a copy of the run with the new placement in ``model.pt``,
    ``covariance.pt`` and ``robot_calibrated.urdf``, and a ``station`` block in ``model.json`` and ``report.json``
    (and a section in ``report.md``)."""
    from torchcal.robot.export import write_urdf

    run_dir = Path(run_dir)
    state = {k: v.cpu() for k, v in model.state_dict().items()}
    if not all(bool(torch.isfinite(v).all()) for k, v in state.items() if v.is_floating_point() and "limits" not in k):
        raise EstimationError("the re-stationed model has non-finite values; nothing was written")
    block = {"from_run": str(run_dir), "points_file": str(points_file), **station.to_dict()}
    report = copy.deepcopy(read_report(run_dir))
    report["station"] = block
    params = report.get("parameters")
    if isinstance(params, dict):
        params["instrument"] = {"T_tracker_base": station.T_tracker_base.tolist()}
        params["tool"] = {"t_flange_probe_m": station.t_flange_probe.tolist()}
    # its kinematic calibration, stand-alone geometry and held-out rows are of the old placement
    meta = {k: v for k, v in meta.items() if k not in ("geometric", "standalone")}
    meta["station"] = {k: block[k] for k in ("from_run", "points_file", "n_points", "lever_arm_fitted", "label")}
    with replace_dir(out, kind="station", inputs=inputs) as tmp:
        for entry in sorted(run_dir.iterdir()):
            if entry.name == MARKER or entry.name.startswith(".") or entry.is_symlink() or entry.name in _OLD_PLACEMENT:
                continue
            if entry.is_file():
                shutil.copy2(entry, tmp / entry.name)
            elif entry.is_dir() and entry.name == "robot":
                (tmp / "robot").mkdir()
                for f in entry.iterdir():
                    if f.is_file() and not f.is_symlink():
                        shutil.copy2(f, tmp / "robot" / f.name)
        torch.save(state, tmp / "model.pt")
        if station.run_covariance is not None:
            torch.save(station.run_covariance.state(), tmp / "covariance.pt")
        (tmp / "model.json").write_text(json.dumps(meta, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        from torchcal.report.rundir import _json_safe

        (tmp / "report.json").write_text(
            json.dumps(_json_safe(report), indent=1, allow_nan=False) + "\n", encoding="utf-8"
        )
        with open(tmp / "report.md", "a", encoding="utf-8") as f:
            f.write(_markdown(station, run_dir, str(points_file)))
        if (tmp / "robot_calibrated.urdf").exists():
            note = f"re-stationed from {run_dir.name} on {block['n_points']} points: tracker frame (and probe) new"
            write_urdf(
                model.robot,
                tmp / "robot_calibrated.urdf",
                notes=[note],
            )
    return Path(out)
