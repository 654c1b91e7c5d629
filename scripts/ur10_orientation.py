#!/usr/bin/env python3
"""The command line of :mod:`experiments.ur10_orientation`: the real UR10's full 6-D pose, position-only
against full-pose calibration on the same grouped held-out split (issue 26, item 4).

The experiment is described there; this script parses the arguments, runs it and prints a table (stderr) and, with
``--json``, the result as one JSON line.
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, ur10_orientation
from experiments.ur10_orientation import METHODS, SERIES, run, table

ap = common.parser(ur10_orientation.__doc__.split("\n\n")[0])
ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_A ... Series_D)")
ap.add_argument("--series", default="B,C,D", help="comma separated, of A,B,C,D (default B,C,D)")
ap.add_argument("--methods", default="kinematic", help="comma separated, of kinematic,auto (default kinematic)")
ap.add_argument("--a-rows", type=int, default=3000, help="Series A: this many seeded rows (0: all; default 3000)")


def experiment(a):
    if not a.data_dir.is_dir():
        ap.error(f"data folder not found: {a.data_dir}")
    names = common.comma_list(ap, a.series, SERIES, what="series", upper=True)
    methods = common.comma_list(ap, a.methods, METHODS, what="method")
    return run(a.data_dir, names, methods, a.a_rows)


def main(argv=None) -> int:
    args, res = common.run(ap, experiment, argv)
    print(table(res), file=sys.stderr)
    common.emit(res, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
