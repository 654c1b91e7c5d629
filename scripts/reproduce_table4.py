#!/usr/bin/env python3
"""Reproduce (and beat) Table 4 and Figs. 9, 11, 12 of Horvath & Neuner (2024): the integrated ANN-EKF.

The experiment is experiments.table4; this writes table4.json, table4.md and the figures into ``--out``,
prints the table to stderr and the result as JSON (``--json``: one line).
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.table4 import markdown, run

ap = common.parser(__doc__)
ap.add_argument("--draws", type=int, default=10)
ap.add_argument("--samples", type=int, default=7342)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--quick", action="store_true", help="2 draws and 3000 samples")
ap.add_argument("--paper-mode", action="store_true", help="also run the paper's re-iteration (slow)")
ap.add_argument("--out", type=Path, default=Path("runs/paper"))


def main(argv=None) -> dict:
    args, result = common.run(
        ap, lambda a: run(*((2, 3000) if a.quick else (a.draws, a.samples)), a.seed, a.paper_mode, a.out), argv
    )
    print(markdown(result), file=sys.stderr)
    common.emit(result, args, plain=result)
    return result


if __name__ == "__main__":
    main()
