#!/usr/bin/env python3
"""Accuracy and speed of the geometric calibration on simulated UR5 campaigns; prints JSON
(experiments.bench_calibration).

    python scripts/bench_calibration.py [--seeds 5] [--json]

With ``--stages DATA --robot R [--method M ...] [--load]`` it instead times one calibration of DATA per method
(default: ``auto``, then ``kinematic``) in a fresh process with one torch thread, stage by stage; prints JSON.
"""

import json
import tempfile
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.bench_calibration import accuracy, compare

ap = common.parser(__doc__, threads=2)
ap.add_argument("--seeds", type=int, default=5)
ap.add_argument("--stages", metavar="DATA", help="time one calibration of DATA stage by stage instead")
ap.add_argument("--robot", default="ur10")
ap.add_argument(
    "--method",
    action="append",
    help="with --stages: the method(s) to time, repeatable (default: auto and kinematic; ratios are to the last)",
)
ap.add_argument("--load", action="store_true", help="with --stages: run again beside a busy process")


def experiment(a) -> dict:
    if a.stages:
        with tempfile.TemporaryDirectory() as tmp:
            return compare(a.stages, a.robot, a.method or ["auto", "kinematic"], a.load, Path(tmp))
    return accuracy(a.seeds)


def main(argv=None) -> dict:
    args, res = common.run(ap, experiment, argv)
    if args.stages:
        print(json.dumps(res))  # the stage timings are always one JSON line
    else:
        common.emit(res, args, plain=res)
    return res


if __name__ == "__main__":
    main()
