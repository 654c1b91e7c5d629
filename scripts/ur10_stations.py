#!/usr/bin/env python3
"""The command line of :mod:`experiments.ur10_stations`: the real UR10's series calibrated together, one
instrument pose per tracker placement and one lever arm per tool.

The experiment and its outputs are described there; this script parses the arguments, runs it and prints.
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, ur10_stations
from experiments.ur10_stations import METHODS, SERIES, markdown, run

ap = common.parser(ur10_stations.__doc__.split("\n\n")[0])
ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_A ... Series_D)")
ap.add_argument("--series", default=",".join(SERIES), help="series, comma separated (default A,B,C,D)")
ap.add_argument("--methods", default=",".join(METHODS), help="methods, comma separated (default kinematic,auto)")
ap.add_argument(
    "--bc-one-station", action="store_true", help="B and C as one tracker placement, as the data's README has them"
)
ap.add_argument("--a-rows", type=int, default=0, help="subsample Series A to this many rows (default 0: all)")


def experiment(a):
    if not a.data_dir.is_dir():
        ap.error(f"data folder not found: {a.data_dir}")
    names = common.comma_list(ap, a.series, SERIES, what="series", upper=True)
    methods = common.comma_list(ap, a.methods, ("kinematic", "auto", "pcm", "kinematic+ann"), what="method")
    res = run(a.data_dir, names, methods, a.a_rows, a.bc_one_station)
    return res, markdown(res)


def main(argv=None) -> int:
    return common.run_markdown(ap, experiment, argv)


if __name__ == "__main__":
    sys.exit(main())
