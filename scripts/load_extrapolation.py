#!/usr/bin/env python3
"""The robot under load: trained at 0 kg, predicting 5 and 10 kg rows (experiments.load_extrapolation, issue 45).

python scripts/load_extrapolation.py [--seed 1] [--poses 200] [--json]
    [--parts masses,torques,lumped,no_load,mixed,clean]
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, load_extrapolation

ap = common.parser(__doc__)
ap.add_argument("--seed", type=int, default=1)
ap.add_argument("--poses", type=int, default=200, help="training poses per campaign (the mixed one: 1.5 times)")
ap.add_argument("--parts", default="masses,torques,lumped,no_load,mixed,clean")


def main(argv=None) -> dict:
    args, out = common.run(ap, lambda a: load_extrapolation.run(a.seed, a.poses, tuple(a.parts.split(","))), argv)
    common.emit(out, args, plain=out)
    return out


if __name__ == "__main__":
    main()
