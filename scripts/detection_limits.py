#!/usr/bin/env python3
"""Detection limits of the closed loop: per effect family, the smallest size it names reliably
(experiments.detection_limits).

    python scripts/detection_limits.py [--seeds 10] [--sizes 5,7.5,10,15,20,30] [--workers 2] [--address ADDR] [--json]
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.detection_limits import FAMILIES, run
from torchcal import _console

ap = common.parser(__doc__)
ap.add_argument("--robot", default="ur5")
ap.add_argument("--families", default=",".join(FAMILIES))
ap.add_argument("--sizes", default="5,7.5,10,15,20,30", help="sizes in um RMS (default 5,7.5,10,15,20,30)")
ap.add_argument("--seeds", type=int, default=10, help="campaigns per family and size (default 10)")
ap.add_argument("--poses", type=int, default=800)
ap.add_argument("--reliable", type=float, default=0.9, help="detection rate that counts as reliable")
ap.add_argument("--first-seed", type=int, default=2000)
common.add_sweep_arguments(ap, "campaigns")


def experiment(a) -> dict:
    families = a.families.split(",")
    sizes = [float(s) for s in a.sizes.split(",")]
    return run(a.robot, families, sizes, a.seeds, a.poses, a.reliable, a.first_seed, a.workers, a.address)


def main(argv=None) -> dict:
    _console.set_quiet(True)
    args, out = common.run(ap, experiment, argv)
    common.emit(out, args, plain=out)
    return out


if __name__ == "__main__":
    main()
