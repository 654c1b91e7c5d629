"""Issue 49's two speed ratios on real UR10 Series C, in one run (``scripts/speed_ratios.py``).

(a) ``torchcal calibrate --method kinematic`` against the numpy reference command
(:mod:`experiments.numpy_reference`, same training rows: calibrate's grouped 80/20 split) plus
``python -c 'import torch'``: the work a torch-based tool cannot avoid; target at most 2.
(b) the default method's ``torchcal calibrate`` against the kinematic one; target at most 2.5.

Every command runs in a fresh process with one thread (:func:`experiments.bench_kinematic._timed`); the measure is
CPU time (user + system of the child, from ``RUSAGE_CHILDREN``), because on a machine shared by many sessions wall
time counts the others' work. Each command is run ``repeats`` times, the commands alternating within a round, and
each one's shortest CPU time is taken; the ratios are of those minima, all from the same run.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

from experiments.bench_kinematic import REFERENCE, _timed, compile_torchcal, torchcal_command, write_problem
from experiments.ipa_series import series_file
from torchcal.data import convert_ipa


def default_command(data: str, robot: str, out: Path) -> list[str]:
    """``torchcal calibrate DATA --robot R --out OUT --quiet`` (the default method, ``python -m torchcal``)."""
    return [sys.executable, "-m", "torchcal", "calibrate", data, "--robot", robot, "--out", str(out), "--quiet"]


def measure(data_dir: Path, work: Path, repeats: int = 3, series: str = "C", default: bool = True) -> dict:
    """Convert ``Series_<series>`` under ``data_dir`` (untimed), then time the commands (module docstring)."""
    data = str(work / f"series_{series.lower()}.csv")
    convert_ipa(series_file(data_dir, series), data)
    problem = work / "problem.json"
    write_problem(data, "ur10", problem)
    compile_torchcal()
    argv = {
        "kinematic": lambda: torchcal_command(data, "ur10", work / "kinematic"),
        "reference": lambda: [sys.executable, str(REFERENCE), data, "--problem", str(problem)],
        "import_torch": lambda: [sys.executable, "-c", "import torch"],
    }
    if default:
        argv["default"] = lambda: default_command(data, "ur10", work / "default")
    runs: dict[str, list[dict]] = {k: [] for k in argv}
    for _ in range(repeats):
        for name, make in argv.items():
            shutil.rmtree(work / name, ignore_errors=True)
            runs[name].append(_timed(make()))
    cpu = {k: min(r["cpu_s"] for r in v) for k, v in runs.items()}
    out = {
        "data": f"Series_{series}",
        "repeats": repeats,
        "measure": "CPU s (user+sys of the child), shortest of the repeats",
        "cpu_s": cpu,
        "runs_cpu_s": {k: [round(r["cpu_s"], 3) for r in v] for k, v in runs.items()},
        "runs_wall_s": {k: [round(r["wall_s"], 3) for r in v] for k, v in runs.items()},
        "ratio_kinematic_vs_reference_plus_torch": cpu["kinematic"] / (cpu["reference"] + cpu["import_torch"]),
        "rmse_holdout_mm": {
            "kinematic": json.loads((work / "kinematic" / "report.json").read_text())["rmse_geometric_mm"],
            "reference": json.loads(runs["reference"][-1]["stdout"].strip().splitlines()[-1])["rmse_holdout_mm"],
        },
        "load_average": os.getloadavg()[0],
    }
    if default:
        out["ratio_default_vs_kinematic"] = cpu["default"] / cpu["kinematic"]
        out["rmse_holdout_mm"]["default"] = json.loads((work / "default" / "report.json").read_text())["rmse_after_mm"]
    return out
