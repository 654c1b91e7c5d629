#!/usr/bin/env python3
"""Held-out RMSE against the number of training poses (experiments.learning_curve).

    python scripts/learning_curve.py --data ../shared/data/real/ur10-ipa --series C,A --out runs/learning_curve
    python scripts/learning_curve.py --data ../shared/data/real/ur10-ipa --series A --sizes 50,100,200,500,1000
    python scripts/learning_curve.py --simulated 300 --sizes 50,100,all --out /tmp/lc   # a UR5 campaign, quick

Writes learning_curve.json, learning_curve.md (tables) and learning_curve.png into --out and prints the tables
(``--json``: the result as one JSON line, last).
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.learning_curve import METHODS, SIZES, parse_sizes, run

ap = common.parser(__doc__)
ap.add_argument("--data", type=Path, default=Path("../shared/data/real/ur10-ipa"), help="the ur10-ipa folder")
ap.add_argument("--series", default="C,A", help="UR10 series, comma separated (default C,A)")
ap.add_argument("--simulated", type=int, default=0, help="a simulated UR5 campaign of this many poses instead")
ap.add_argument("--sizes", default=",".join(map(str, SIZES)), help="training sizes (integers and 'all')")
ap.add_argument("--methods", default=",".join(METHODS), help="calibrate methods (default kinematic,auto)")
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--out", type=Path, default=Path("runs/learning_curve"))


def experiment(a):
    try:
        sizes = parse_sizes(a.sizes)
    except ValueError as err:
        ap.error(str(err))
    series = list(common.comma_list(ap, a.series, upper=True))
    return run(a.data, series, a.simulated, sizes, common.comma_list(ap, a.methods), a.seed, a.out)


def main(argv=None) -> int:
    return common.run_markdown(ap, experiment, argv)


if __name__ == "__main__":
    sys.exit(main())
