#!/usr/bin/env python3
"""Probe a calibration just outside its data (experiments.edge_probe); prints JSON.

    python scripts/edge_probe.py probe DATA.csv --robot ur5
    python scripts/edge_probe.py probe ../shared/data/real/ur10-ipa/Series_C/measurements_random_poses.csv \\
        --robot ur10 --format ipa
    python scripts/edge_probe.py home ../shared/data/real/ur10-ipa/Series_C/measurements_random_poses.csv \\
        --robot ur10 --format ipa --home=-3.14159,-1.5708,0,-1.5708,0,0

``probe``: the largest correction (method minus kinematic) on poses 0.1-0.6 rad beyond one joint's range over its
largest on the training poses. ``home``: a grouped 80/20 split holding the home pose out, both methods' held-out
errors and the error at the home pose.
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, edge_probe

ap = common.parser(__doc__)
ap.add_argument("what", choices=("probe", "home"))
ap.add_argument("data", type=Path, help="measurement file")
ap.add_argument("--robot", required=True, help="robot name or file")
ap.add_argument("--format", choices=("csv", "ipa"), default="csv", help="csv: the contract's; ipa: a UR10 series")
ap.add_argument("--method", default="auto", help="the method judged against kinematic (default auto)")
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--per-side", type=int, default=25, help="probe: probes per joint and side (default 25)")
ap.add_argument("--home", default=None, help="home: the pose to hold out, comma-separated joints [rad]")


def experiment(a):
    if not a.data.is_file():
        ap.error(f"data file not found: {a.data}")
    if a.what == "probe":
        return edge_probe.run(a.data, a.robot, seed=a.seed, per_side=a.per_side, method=a.method, fmt=a.format)
    if a.home is None:
        ap.error("home needs --home")
    try:
        home = [float(v) for v in a.home.split(",")]
    except ValueError:
        ap.error(f"--home must be comma-separated numbers, got {a.home!r}")
    return edge_probe.home_split(a.data, a.robot, home, seed=a.seed, method=a.method, fmt=a.format)


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
    sys.exit(0)
