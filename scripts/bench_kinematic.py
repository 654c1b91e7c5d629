#!/usr/bin/env python3
"""``torchcal calibrate --method kinematic`` against a plain numpy Gauss-Newton reference on the same rows; prints
JSON (experiments.bench_kinematic, experiments.numpy_reference).

    python scripts/bench_kinematic.py series_c.csv --robot ur10 [--repeats 3] [--bytecode "as found"] --json

Both as commands in fresh processes with one thread, alternating, the shortest of ``--repeats`` each (wall and CPU
seconds), then each fit alone in this process; ``ratio`` is torchcal over the reference. Also prints both held-out
RMSEs (the same rows: calibrate's grouped 80/20 split).
"""

import tempfile
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.bench_kinematic import compare

ap = common.parser(__doc__)
ap.add_argument("data", help="measurement file (CONTRACT.md section 1) of a standard-DH robot")
ap.add_argument("--robot", default="ur10")
ap.add_argument("--repeats", type=int, default=3)
ap.add_argument(
    "--bytecode",
    choices=("compiled", "as found"),
    default="compiled",
    help="compile torchcal to bytecode first, as an installed package has it (default), or run it as found",
)


def experiment(a) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        return compare(a.data, a.robot, Path(tmp), a.repeats, a.bytecode)


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
