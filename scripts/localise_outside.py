#!/usr/bin/env python3
"""Localise and identify one undeclared effect after a kinematic calibration; held-out RMSE of geometry + it
(experiments.localise_outside). Prints one JSON object.

    python scripts/localise_outside.py --outside ../shared/data/outside --simulated
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.localise_outside import run

ap = common.parser(__doc__)
ap.add_argument("--outside", type=Path, help="folder of outside campaigns (with index.json)")
ap.add_argument(
    "--campaigns",
    nargs="*",
    default=["cyclic-s808", "cyclic_hi-s404", "warmup-s404", "jointscale-s404", "drift-s808", "none-s808"],
)
ap.add_argument("--simulated", action="store_true", help="also the formula campaigns of torchcal.sim.outside")
ap.add_argument("--seed", type=int, default=100)
ap.add_argument("--clean", type=int, default=0, help="N clean formula campaigns: family-wise p of localisation")


def main(argv=None) -> int:
    args, res = common.run(ap, lambda a: run(a.outside, a.campaigns, a.simulated, a.seed, a.clean), argv)
    common.emit(res, args, plain=res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
