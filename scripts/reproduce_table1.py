#!/usr/bin/env python3
"""Reproduce Table 1 and Fig. 5 of Horvath & Neuner (2024): which DH biases the tracker pose and lever arm absorb.

The experiment is experiments.table1; this prints the table (``--json``: and the result as one JSON
object on the last line) and writes table1.json, table1.md and fig5.png into ``--out``.
"""

import sys

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.table1 import add_arguments, fill_sizes, run, script_main, text_table, write_outputs

SIZES = {"draws": (20, 5, "Monte Carlo draws per parameter"), "poses": (300, 150, "random visible poses")}
ap = common.parser(__doc__)
add_arguments(ap, SIZES)


def experiment(a) -> dict:
    fill_sizes(a, SIZES)
    if a.draws < 1 or a.poses < 10:
        ap.error(f"need --draws >= 1 and --poses >= 10, got {a.draws} and {a.poses}")
    return run(a.draws, a.poses, a.seed, a.posture)


def main(argv: list[str] | None = None) -> int:
    return script_main(ap, experiment, write_outputs, text_table, argv)


if __name__ == "__main__":
    sys.exit(main())
