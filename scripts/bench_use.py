#!/usr/bin/env python3
"""CPU and wall time of ``torchcal predict``, ``compensate`` and ``plan`` against a baseline source tree, in one run
(experiments.bench_use): each case as a command, the import included, this tree and the baseline alternating,
under the default torch threads (what a user gets) and under one (``OMP_NUM_THREADS=1``); the outputs of both
trees are compared number by number. Prints JSON.

The baseline is a torchcal source tree, e.g. the commit before the speed-up, and the run a calibration of real data
(docs/real-data.md):

    git worktree add /tmp/base-fast 07f890c
    torchcal convert --from ipa-robot-accuracy PATH/TO/ur10-ipa/Series_C/measurements_random_poses.csv --out c.csv
    torchcal calibrate --robot ur10 c.csv --out /tmp/runC
    python scripts/bench_use.py --baseline /tmp/base-fast --run /tmp/runC --data c.csv --targets TARGETS.csv \\
        [--plan-n 100] [--threads-env default,1] [--repeat 1] [--json]
"""

import sys
import tempfile
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import bench_use, common

HERE = Path(__file__).resolve().parents[1]

ap = common.parser(__doc__)
ap.add_argument("--baseline", required=True, help="a torchcal source tree to compare with")
ap.add_argument("--run", help="a run directory written by calibrate (for predict and compensate)")
ap.add_argument("--data", help="rows to predict (a measurement file of the run's robot)")
ap.add_argument("--targets", help="targets to compensate (x,y,z and/or q1..qN, as compensate reads them)")
ap.add_argument("--plan-n", default="", help="plan --n N of --robot, comma-separated, one case each (default none)")
ap.add_argument("--robot", default="ur5", help="the robot of the plan cases")
ap.add_argument("--threads-env", default="default,1", help="thread settings, comma-separated: default and/or a number")
ap.add_argument("--repeat", type=int, default=1, help="runs of each tree per case (the fastest counts)")


def run(args) -> dict:
    base = Path(args.baseline).resolve()
    plan_n = [int(n) for n in common.comma_list(ap, args.plan_n)]
    todo = bench_use.cases(args.run, args.data, args.targets, plan_n, args.robot)
    if not todo:
        ap.error("nothing to time: give --run with --data and/or --targets, or --plan-n")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cache = tmp / "pycache"
        for tree in (HERE, base):
            bench_use.compile_tree(tree, cache)
        results = [
            bench_use.compare(base, HERE, case, threads, args.repeat, tmp, cache)
            for case in todo
            for threads in common.comma_list(ap, args.threads_env)
        ]
    return {"baseline": str(base), "cases": results}


def main(argv=None) -> dict:
    args, out = common.run(ap, run, argv)
    for c in out["cases"]:
        print(", ".join(f"{k} {v}" for k, v in c.items()), file=sys.stderr)
    common.emit(out, args)
    return out


if __name__ == "__main__":
    main()
