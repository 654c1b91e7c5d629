#!/usr/bin/env python3
"""False-positive rate of the closed loop: clean simulated campaigns (geometry only) over many seeds
(experiments.false_positives).

    python scripts/false_positives.py [--seeds 100] [--poses 800] [--trajectories 10] [--workers 2] [--address ADDR]
        [--payload-levels 0,5,10] [--torques] [--stations 3] [--json]
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.false_positives import run
from torchcal import _console

ap = common.parser(__doc__)
ap.add_argument("--robot", default="ur5")
ap.add_argument("--seeds", type=int, default=100, help="static campaigns (default 100)")
ap.add_argument("--poses", type=int, default=800, help="poses per static campaign (default 800)")
ap.add_argument("--trajectories", type=int, default=10, help="trajectory campaigns (default 10)")
ap.add_argument("--samples", type=int, default=3000, help="samples per trajectory (default 3000)")
ap.add_argument("--first-seed", type=int, default=1000)
ap.add_argument(
    "--payload-levels",
    default=None,
    help="the static campaigns' rows cycle over these payloads [kg] (load columns: the load candidates are offered)",
)
ap.add_argument("--torques", action="store_true", help="the static campaigns' rows carry measured joint torques")
ap.add_argument(
    "--stations",
    type=int,
    default=1,
    help="instrument placements of each static campaign (default 1; several: the instrument terms are offered)",
)


def _load(a) -> dict | None:
    levels = None if a.payload_levels is None else tuple(float(v) for v in a.payload_levels.split(","))
    if levels is None and not a.torques:
        return None
    return {"payload_levels": levels, "torques": a.torques}


common.add_sweep_arguments(ap, "campaigns")


def main(argv=None) -> dict:
    _console.set_quiet(True)
    args, out = common.run(
        ap,
        lambda a: run(
            a.robot,
            a.seeds,
            a.poses,
            a.trajectories,
            a.samples,
            a.first_seed,
            a.workers,
            a.address,
            _load(a),
            a.stations,
        ),
        argv,
    )
    common.emit(out, args, plain={k: v for k, v in out.items() if k != "rows"})
    return out


if __name__ == "__main__":
    main()
