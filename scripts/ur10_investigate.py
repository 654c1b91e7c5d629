#!/usr/bin/env python3
"""The command line of :mod:`experiments.ur10_investigate`: what remains on the real UR10 after the
geometric fit (issue 5, item 5): noise, configuration, reach, drift.

The experiment and its outputs are described there; this script parses the arguments, runs it and prints.
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, ur10_investigate
from experiments.ur10_investigate import SERIES, run, summary

ap = common.parser(ur10_investigate.__doc__.split("\n\n")[0])
ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_A ... Series_D)")
ap.add_argument("--series", default=",".join(SERIES), help="comma separated (default A,B,C,D)")
ap.add_argument("--a-rows", type=int, default=3000, help="Series A: fit on this many seeded rows (0: all)")
ap.add_argument("--pair-rows", type=int, default=3000, help="rows for the correlation curves (seeded subsample)")
ap.add_argument("--tol", type=float, default=1e-3, help="revisit: every joint within this [rad] (default 1e-3)")


def experiment(a):
    if not a.data_dir.is_dir():
        ap.error(f"data folder not found: {a.data_dir}")
    names = common.comma_list(ap, a.series, SERIES, what="series", upper=True)
    return run(a.data_dir, names, a.a_rows, a.pair_rows, a.tol)


def main(argv=None) -> int:
    args, res = common.run(ap, experiment, argv)
    print(summary(res), file=sys.stderr)
    common.emit(res, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
