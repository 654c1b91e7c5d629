"""What the global test says on plain campaigns: the real UR10 series (ipa-robot-accuracy) and the outside campaigns.

Each campaign is calibrated as ``torchcal calibrate`` does (the method given, seed 0) and its report's
``global_test`` read (:func:`torchcal.diagnose.noise.global_test_reading`): the variance factor, the instrument's
noise level and where it came from, what the model leaves in it, the geometric fit's share of the reach, and the
reading. A false alarm is a plain campaign read as a unit or robot-description mistake (``reading == "mistake"``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from experiments.ipa_series import series_file


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
