#!/usr/bin/env python3
"""Beyond the joints a campaign saw (issue 51; experiments.narrow_campaigns): simulated narrow UR5 campaigns, prints
JSON.

    python scripts/narrow_campaigns.py --json
    python scripts/narrow_campaigns.py --seeds 0,1,2,3,4 --poses 300 --test-poses 200 --json

Each campaign holds joints 1, 4, 5 and 6 within --width-deg (default 1) while joints 2 and 3 range; the test poses
range over the whole workspace; with and without compliance of joints 2 and 3 (1.5e-5 and 1e-5 rad/(N m)). Printed
per campaign: the test RMSE of the nominal robot with its instrument pose and lever arm fitted, of the kinematic
method and of the default method, and for the two calibrations the share of test rows within 3 sigma, the median
|error| / sigma, which model predicted each row (`models`) and which the run chose for its rows beyond the region,
on what evidence (`beyond`: model, evidence, n_evidence, each candidate's RMSE there); then whether issue 51's
targets hold in every campaign.
"""

import sys

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, narrow_campaigns

ap = common.parser(__doc__)
ap.add_argument("--seeds", default="0,1,2", help="campaign seeds, comma separated (default 0,1,2)")
ap.add_argument("--poses", type=int, default=300, help="training poses per campaign (default 300)")
ap.add_argument("--test-poses", type=int, default=200, help="test poses per campaign (default 200)")
ap.add_argument("--width-deg", type=float, default=1.0, help="band of the held joints [deg] (default 1)")


def experiment(a):
    try:
        seeds = tuple(int(s) for s in a.seeds.split(","))
    except ValueError:
        ap.error(f"--seeds must be whole numbers separated by commas, got {a.seeds!r}")
    return narrow_campaigns.run(seeds, poses=a.poses, test_poses=a.test_poses, width_deg=a.width_deg)


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
    sys.exit(0)
