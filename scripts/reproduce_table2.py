#!/usr/bin/env python3
"""Reproduce Table 2 of Horvath & Neuner (2024): the kinematic calibration with the paper's fixed parameters.

The experiment is experiments.table2; this prints the table (``--json``: and the result as one JSON
object on the last line) and writes table2.json and table2.md into ``--out``.
"""

import sys

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.table1 import add_arguments, fill_sizes, script_main
from experiments.table2 import run, text_table, write_outputs

SIZES = {
    "draws": (20, 3, "Monte Carlo draws per variant"),
    "poses": (300, 150, "calibration poses"),
    "test_poses": (100, 50, "held-out poses"),
}
ap = common.parser(__doc__)
add_arguments(ap, SIZES)


def experiment(a) -> dict:
    fill_sizes(a, SIZES)
    if a.draws < 1 or a.poses < 60 or a.test_poses < 1:
        ap.error(f"need --draws >= 1, --poses >= 60, --test-poses >= 1, got {a.draws}, {a.poses}, {a.test_poses}")
    return run(a.draws, a.poses, a.test_poses, a.seed, a.posture)


def main(argv: list[str] | None = None) -> int:
    return script_main(ap, experiment, write_outputs, text_table, argv)


if __name__ == "__main__":
    sys.exit(main())
