#!/usr/bin/env python3
"""The command line of :mod:`experiments.restation`: calibrate one series of the real UR10 (ipa-robot-accuracy
data), re-station it on a few points of another series and predict that series' held-out poses."""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, restation

ap = common.parser(restation.__doc__.split("\n\n")[0])
ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_A ... Series_D)")
ap.add_argument("--fit-series", default="A", help="series to calibrate (default A)")
ap.add_argument("--target", default="D", help="series to re-station on and predict (default D)")
ap.add_argument("--points", type=int, default=6, help="points to re-station on (default 6)")
ap.add_argument("--seeds", type=int, default=5, help="random draws of the points (default 5)")
ap.add_argument("--methods", default="kinematic", help="calibration methods of the fit series (default kinematic)")
ap.add_argument("--no-tool", action="store_true", help="hold the lever arm (default: fit it, another tool)")
common.add_sweep_arguments(ap, "re-stationings")


def experiment(a):
    if not a.data_dir.is_dir():
        ap.error(f"data folder not found: {a.data_dir}")
    methods = tuple(common.comma_list(ap, a.methods, None, what="method"))
    res = restation.run(
        a.data_dir,
        a.fit_series.upper(),
        a.target.upper(),
        a.points,
        a.seeds,
        methods,
        tool=not a.no_tool,
        workers=a.workers,
        address=a.address,
    )
    return res, restation.markdown(res)


def main(argv=None) -> int:
    return common.run_markdown(ap, experiment, argv)


if __name__ == "__main__":
    sys.exit(main())
