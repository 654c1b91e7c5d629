#!/usr/bin/env python3
"""The command line of :mod:`experiments.trust_level_by_pose`: a constant level of the unexplained error against one
regressed on the pose, judged on a campaign's test rows. Prints one JSON line.

    python scripts/trust_level_by_pose.py PATH/TO/outside/jointscale-s404 [--method kinematic] --json
"""

from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, trust_level_by_pose

ap = common.parser(__doc__)
ap.add_argument("folder", type=Path, help="a campaign folder with train.csv and test.csv")
ap.add_argument("--robot", default="ur5", help="the campaign's robot (default ur5: the outside campaigns)")
ap.add_argument("--method", default="kinematic", help="calibration method (default kinematic)")


def experiment(a):
    if not (a.folder / "train.csv").is_file() or not (a.folder / "test.csv").is_file():
        ap.error(f"{a.folder}: expected a folder with train.csv and test.csv")
    return trust_level_by_pose.run(a.folder, a.robot, a.method)


def main(argv=None) -> dict:
    args, result = common.run(ap, experiment, argv)
    common.emit(result, args, plain=result)
    return result


if __name__ == "__main__":
    main()
