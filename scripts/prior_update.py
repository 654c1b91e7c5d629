#!/usr/bin/env python3
"""The command line of :mod:`experiments.prior_update`: calibrate a series of the real UR10, simulate a
crash of one joint, and update the calibration from a few crashed rows (``calibrate --prior``)."""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, prior_update

ap = common.parser(prior_update.__doc__.split("\n\n")[0])
ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_A ... Series_D)")
ap.add_argument("--series", default="C", help="series to calibrate (default C)")
ap.add_argument("--rows", type=int, default=10, help="crashed training rows to update from (default 10)")
ap.add_argument("--seeds", type=int, default=5, help="random draws of the rows, torch.randperm (default 5)")
ap.add_argument(
    "--draws",
    type=int,
    default=None,
    help="random draws of the rows with numpy.random.default_rng(seed), seeds 0..N-1 (issue 34's protocol; "
    "replaces --seeds)",
)
ap.add_argument("--joint", "--shift-joint", type=int, default=2, help="the crashed joint, 1-based (default 2)")
shift = ap.add_mutually_exclusive_group()
shift.add_argument("--shift-mrad", type=float, default=None, help="its readings' shift [mrad] (default 2)")
shift.add_argument("--shift", type=float, default=None, help="its readings' shift [rad] (e.g. -0.002)")
ap.add_argument(
    "--method",
    choices=("kinematic", "auto"),
    default="kinematic",
    help="the method of the calibration before the crash and of the update (default kinematic; auto: the default)",
)
common.add_sweep_arguments(ap, "draws")


def experiment(a):
    if not a.data_dir.is_dir():
        ap.error(f"data folder not found: {a.data_dir}")
    shift = a.shift if a.shift is not None else (a.shift_mrad if a.shift_mrad is not None else 2.0) * 1e-3
    draws, how = (a.draws, "numpy") if a.draws is not None else (a.seeds, "torch")
    res = prior_update.run(
        a.data_dir, a.series.upper(), a.rows, draws, a.joint, shift, a.method, how, a.workers, a.address
    )
    return res, prior_update.markdown(res)


def main(argv=None) -> int:
    return common.run_markdown(ap, experiment, argv)


if __name__ == "__main__":
    sys.exit(main())
