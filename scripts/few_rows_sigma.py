#!/usr/bin/env python3
"""The command line of :mod:`experiments.few_rows_sigma`: predict's sigma of small single-station runs (8 held-out
rows) on many fresh test rows. Prints one JSON line.

    python scripts/few_rows_sigma.py [--robots ur5,fanuc_like,ur10_track] [--seeds 1,2,3,4] [--method auto] --json
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, few_rows_sigma

ap = common.parser(__doc__)
ap.add_argument("--robots", default=",".join(few_rows_sigma.ROBOTS), help="of " + ", ".join(few_rows_sigma.ROBOTS))
ap.add_argument("--seeds", default="1,2,3,4", help="comma-separated campaign seeds")
ap.add_argument("--poses", type=int, default=40, help="training poses (20 %% held out; default 40)")
ap.add_argument("--test-poses", type=int, default=200, help="fresh test rows per campaign (default 200)")
ap.add_argument("--method", default="auto", help="calibration method (default auto)")


def experiment(a):
    robots = tuple(r.strip() for r in a.robots.split(",") if r.strip())
    bad = [r for r in robots if r not in few_rows_sigma.ROBOTS]
    if bad or not robots:
        ap.error(f"--robots must name some of {', '.join(few_rows_sigma.ROBOTS)}, got {a.robots!r}")
    seeds = tuple(int(s) for s in a.seeds.split(","))
    return few_rows_sigma.run(robots, seeds, a.poses, a.test_poses, a.method)


def main(argv=None) -> dict:
    args, result = common.run(ap, experiment, argv)
    common.emit(result, args, plain=result)
    return result


if __name__ == "__main__":
    main()
