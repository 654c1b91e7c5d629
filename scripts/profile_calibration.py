#!/usr/bin/env python3
"""Where the default method's time goes: per stage (wall and CPU) and per kernel (cProfile, CPU) of one calibration
of each data set, each in a fresh process with one torch thread; prints JSON (experiments.profile_calibration).

    python scripts/profile_calibration.py --data series_c.csv --robot ur10 [--simulate panda] [--json]
    python scripts/profile_calibration.py --data series_c.csv --robot ur10 --baseline /tmp/base [--repeat 3] [--json]
    python scripts/profile_calibration.py --data train.csv --robot ur5 --commits BEFORE:AFTER [...] [--repeat 10]

``--simulate R`` adds a simulated campaign of robot R (a 6-D probe's orientations, a compliance at joint 2;
``--poses``, ``--seed``). ``--baseline TREE`` instead times the default method of this tree against that of TREE (a
torchcal source tree, e.g. ``git worktree add /tmp/base COMMIT``) on --data as commands, alternating ``--repeat``
times, with this tree's kinematic method in every round; CPU seconds are the measure on a shared machine.
``--commits BEFORE:AFTER`` times the default method of commits of this checkout in pairs (a change against the code
before it), the order flipped every round.
"""

import json
import tempfile
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.profile_calibration import compare, compare_commits, profile, simulated

ap = common.parser(__doc__)
ap.add_argument("--data", help="a measurement file to calibrate")
ap.add_argument("--robot", default="ur10", help="the robot of --data (default ur10)")
ap.add_argument("--simulate", metavar="ROBOT", help="also a simulated campaign of this robot (e.g. panda, 7 axes)")
ap.add_argument("--poses", type=int, default=800, help="poses of the simulated campaign (default 800)")
ap.add_argument("--seed", type=int, default=1, help="seed of the simulated campaign (default 1)")
ap.add_argument("--method", default="auto", help="the method to profile (default auto, the default method)")
ap.add_argument("--baseline", metavar="TREE", help="time the default method against this torchcal source tree instead")
ap.add_argument("--commits", nargs="+", metavar="BEFORE:AFTER", help="time pairs of commits of this checkout instead")
ap.add_argument("--repeat", type=int, default=3, help="with --baseline or --commits: rounds, alternating (default 3)")


def experiment(a) -> dict:
    if not a.data and not a.simulate:
        ap.error("give --data FILE or --simulate ROBOT (or both)")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if (a.baseline or a.commits) and not a.data:
            ap.error("--baseline and --commits time --data: give a measurement file")
        if a.commits:
            pairs = [tuple(p.split(":")) for p in a.commits]
            if any(len(p) != 2 or not all(p) for p in pairs):
                ap.error("--commits takes BEFORE:AFTER pairs, e.g. 6305d8e:0280a7e")
            return compare_commits(a.data, a.robot, pairs, a.repeat, work)
        if a.baseline:
            return compare(a.data, a.robot, Path(a.baseline).resolve(), a.repeat, work)
        if a.data:
            runs.append(profile(a.data, a.robot, a.method, work / "data"))
        if a.simulate:
            train = simulated(a.simulate, a.poses, a.seed, work)
            runs.append(profile(str(train), a.simulate, a.method, work / "simulated"))
            runs[-1]["data"] = f"simulated {a.simulate}: {a.poses} poses, seed {a.seed}, orientation, compliance:2"
    return {"runs": runs}


def main(argv=None) -> dict:
    args, res = common.run(ap, experiment, argv)
    if args.json:
        print(json.dumps(res))
    else:
        print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
