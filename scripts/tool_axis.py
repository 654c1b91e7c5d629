#!/usr/bin/env python3
"""A campaign whose tool axis hardly turns: the lever arm held at its prior, errors on turned-over poses
(experiments.tool_axis). Prints one JSON object.

    python scripts/tool_axis.py --poses 200 --spread 0.03 --seed 1
"""

import sys

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.tool_axis import CASES, run

ap = common.parser(__doc__)
ap.add_argument("--robot", default="ur5")
ap.add_argument("--poses", type=int, default=200, help="training poses (default 200)")
ap.add_argument("--test-poses", type=int, default=60, help="test poses and turned poses, each (default 60)")
ap.add_argument("--spread", type=float, default=0.03, help="largest turn of the tool axis [deg] (default 0.03)")
ap.add_argument("--seed", type=int, default=1)
ap.add_argument("--cases", default=",".join(CASES), help=f"comma separated, of {', '.join(CASES)}")


def main(argv=None) -> int:
    def experiment(a):
        cases = tuple(x for x in a.cases.split(",") if x)
        bad = [x for x in cases if x not in CASES]
        if bad:
            ap.error(f"unknown case(s) {', '.join(bad)}; cases: {', '.join(CASES)}")
        return run(a.robot, a.poses, a.test_poses, a.spread, a.seed, cases)

    args, res = common.run(ap, experiment, argv)
    common.emit(res, args, plain=res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
