#!/usr/bin/env python3
"""The command line of :mod:`experiments.ur10_real`: calibrate the real UR10 (ipa-robot-accuracy data,
Leica tracker + T-Mac) and test across series.

The experiment and its outputs are described there; this script parses the arguments, runs it and prints.
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)
import torch

from experiments import common, ur10_real
from experiments.ur10_real import METHODS, PAIRS, SERIES, run

# the default keeps torch's own thread count; 1 is steadier on a shared, busy machine
ap = common.parser(ur10_real.__doc__.split("\n\n")[0], threads=torch.get_num_threads())
ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_A ... Series_D)")
ap.add_argument("--out", type=Path, default=Path("runs/ur10"), help="output folder (default runs/ur10/)")
ap.add_argument("--quick", action="store_true", help="series C, kinematic only, plus C -> B")
ap.add_argument("--series", default=",".join(SERIES), help="series for part 1, comma separated (default A,B,C,D)")
ap.add_argument("--methods", default=",".join(METHODS), help="methods for part 1 (default all)")
ap.add_argument("--no-transfer", action="store_true", help="skip part 2 (across series)")
ap.add_argument("--a-rows", type=int, default=0, help="subsample Series A to this many rows (default 0: all)")


def experiment(a):
    if not a.data_dir.is_dir():
        ap.error(f"data folder not found: {a.data_dir}")
    if a.quick:
        names, methods, pairs = ("C",), ("kinematic",), (("C", "B"),)
    else:
        names = common.comma_list(ap, a.series, SERIES, what="series", upper=True)
        methods = common.comma_list(ap, a.methods, METHODS, what="method")
        pairs = () if a.no_transfer else PAIRS
    return run(a.data_dir, names, methods, pairs, a.a_rows, a.quick, a.out)


def main(argv=None) -> int:
    return common.run_markdown(ap, experiment, argv)


if __name__ == "__main__":
    sys.exit(main())
