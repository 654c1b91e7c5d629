#!/usr/bin/env python3
"""The closed loop against issue 5's targets on simulated UR5 campaigns (experiments.loop_targets).

python scripts/closed_loop.py [--seeds 3] [--workers 2] [--address ADDR] [--json]
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, loop_targets

ap = common.parser(__doc__)
ap.add_argument("--seeds", type=int, default=3)
ap.add_argument("--poses", type=int, default=800)
ap.add_argument("--first-seed", type=int, default=3000)
common.add_sweep_arguments(ap, "campaigns")


def main(argv=None) -> dict:
    args, out = common.run(ap, lambda a: loop_targets.run(a.seeds, a.poses, a.first_seed, a.workers, a.address), argv)
    common.emit(out, args, plain={k: v for k, v in out.items() if k != "rows"})
    return out


if __name__ == "__main__":
    main()
