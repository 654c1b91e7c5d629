#!/usr/bin/env python3
"""Peak memory and time of each stage of a calibration, each command in a fresh process with one torch thread
(experiments.bench_memory).

    python scripts/bench_memory.py --data series_c.csv --robot ur10 --method kinematic [--json]
    python scripts/bench_memory.py --simulate 50000 --robot ur10 --method kinematic [--json]

Prints a table per command (stage, calls, wall and CPU seconds, the stage's own peak resident memory, resident
memory before and after it); ``--json`` prints the measurements as one JSON object on the last line instead.
``--target MODULE:ATTR=NAME`` (repeatable) adds a stage, e.g.
``--target torchcal.estimate.robust:snooping_statistics=snooping``.
"""

import sys
import tempfile
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.bench_memory import calibration, campaign, table

ap = common.parser(__doc__)
src = ap.add_mutually_exclusive_group(required=True)
src.add_argument("--data", help="measurement file to calibrate")
src.add_argument("--simulate", type=int, metavar="N", help="simulate an N-row campaign, then calibrate it")
ap.add_argument("--robot", default="ur10")
ap.add_argument("--method", default="kinematic")
ap.add_argument("--seed", type=int, default=1, help="with --simulate: the campaign's seed (default 1)")
ap.add_argument("--target", action="append", default=[], help="MODULE:ATTR=NAME, a further stage (repeatable)")


def experiment(a) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        if a.data:
            return {"calibrate": calibration(a.data, a.robot, a.method, Path(tmp) / "run", targets=a.target)}
        return campaign(a.simulate, a.robot, a.method, Path(tmp), seed=a.seed, targets=a.target)


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    if not args.json:
        print("\n\n".join(table(r) for r in result.values()), file=sys.stderr)
    common.emit(result, args)
