"""What the global test says on plain campaigns: the real UR10 series (ipa-robot-accuracy) and the outside campaigns.

Each campaign is calibrated as ``torchcal calibrate`` does (the method given, seed 0) and its report's
``global_test`` read (:func:`torchcal.diagnose.noise.global_test_reading`): the variance factor, the instrument's
noise level and where it came from, what the model leaves in it, the geometric fit's share of the reach, and the
reading. A false alarm is a plain campaign read as a unit or robot-description mistake (``reading == "mistake"``).

:func:`mistakes` makes the other side: a simulated UR5 campaign calibrated with its joints or positions in another
unit (read as radians and metres). Each mistake must be caught: refused by the geometric fit's guard (corrections many
times their priors) or read as a mistake (the unit hint); a mistake read as ``model`` or ``agrees`` is a miss.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

from experiments.ipa_series import series_file

#: the unit mistakes :func:`mistakes` makes: a name, which column group, and the factor the file's numbers carry
MISTAKES = (
    ("joints in degrees read as radians", "q", 180 / math.pi),
    ("joints in gon read as radians", "q", 200 / math.pi),
    ("joints in gon read as degrees", "q", 10 / 9),
    ("positions in mm read as m", "p", 1e3),
    ("positions in cm read as m", "p", 1e2),
    ("positions in inches read as m", "p", 1 / 0.0254),
    ("positions in m read as mm", "p", 1e-3),
)


def _one(name: str, robot: str, data, method: str) -> dict:
    from torchcal.pipeline import Options, calibrate
    from torchcal.report.rundir import build_report

    t0 = time.perf_counter()
    run = calibrate(robot, data, Options.of(method=method, seed=0))
    gt = build_report(run)["global_test"]
    return {
        "campaign": name,
        "method": method,
        "variance_factor": gt["statistic"],
        "threshold": gt["threshold"],
        "noise_um": gt["noise"]["sigma_m"] * 1e6,
        "noise_source": gt["noise"]["source"],
        "unexplained_mm": gt["unexplained_mm"],
        "times_noise": gt["times_noise"],
        "geometric_share_of_reach": gt["geometric_share_of_reach"],
        "reading": gt["reading"],
        "seconds": time.perf_counter() - t0,
    }


def run(ipa_dir: str | None, series: list[str], outside_dir: str | None, method: str) -> dict:
    """Calibrate every campaign named and count the false alarms (module docstring)."""
    from torchcal.data import read_ipa, read_measurements

    rows = []
    for s in series if ipa_dir else []:
        rows.append(_one(f"ur10-ipa Series {s}", "ur10", read_ipa(series_file(Path(ipa_dir), s)), method))
    if outside_dir:
        index = json.loads((Path(outside_dir) / "index.json").read_text(encoding="utf-8"))
        for entry in index:
            path = Path(outside_dir) / entry["dir"] / "train.csv"
            rows.append(_one(f"outside {entry['dir']}", "ur5", read_measurements(path), method))
    failed = [r for r in rows if r["variance_factor"] > r["threshold"]]
    return {
        "method": method,
        "campaigns": len(rows),
        "global_test_failed": len(failed),
        "false_alarms": sum(r["reading"] == "mistake" for r in rows),
        "rows": rows,
    }


def mistakes(method: str, seed: int = 3, poses: int = 200) -> dict:
    """Calibrate a simulated UR5 campaign (``poses`` rows, ``seed``) as it is and with each of :data:`MISTAKES`; count
    those caught (refused, or read as a mistake) and those missed."""
    from torchcal.errors import TorchcalError
    from torchcal.pipeline import Options, calibrate
    from torchcal.report.rundir import build_report
    from torchcal.sim import SimConfig, simulate

    m = simulate(SimConfig(robot="ur5", poses=poses, test_poses=0, seed=seed)).train
    rows = []
    for name, col, factor in (("plain", "q", 1.0), *MISTAKES):
        data = dataclasses.replace(m, **{col: getattr(m, col) * factor})
        t0 = time.perf_counter()
        try:
            gt = build_report(calibrate("ur5", data, Options.of(method=method, seed=0)))["global_test"]
            row = {"reading": gt["reading"], "variance_factor": gt["statistic"]}
            row["geometric_share_of_reach"] = gt["geometric_share_of_reach"]
        except TorchcalError as e:
            row = {"reading": "refused", "error": str(e).splitlines()[0][:160]}
        rows.append({"mistake": name, **row, "seconds": time.perf_counter() - t0})
    made = rows[1:]
    return {
        "method": method,
        "plain_reading": rows[0]["reading"],
        "mistakes": len(made),
        "read_as_mistake": sum(r["reading"] == "mistake" for r in made),
        "refused": sum(r["reading"] == "refused" for r in made),
        "missed": sum(r["reading"] not in ("mistake", "refused") for r in made),
        "rows": rows,
    }
