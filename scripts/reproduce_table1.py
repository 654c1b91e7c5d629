#!/usr/bin/env python3
"""Reproduce Table 1 and Fig. 5 of Horvath & Neuner (2024): which DH biases the tracker pose and lever arm absorb.

The experiment is torchcal.experiments.table1; this prints the table (``--json``: and the result as one JSON
object on the last line) and writes table1.json, table1.md and fig5.png into ``--out``.
"""

import sys
from pathlib import Path

from torchcal.experiments import common
from torchcal.experiments.table1 import POSTURES, run, text_table, write_outputs

ap = common.parser(__doc__)
ap.add_argument("--draws", type=int, default=None, help="Monte Carlo draws per parameter (default 20, quick 5)")
ap.add_argument("--poses", type=int, default=None, help="random visible poses (default 300, quick 150)")
ap.add_argument("--seed", type=int, default=0, help="seed of the poses, tracker, lever arm and biases")
ap.add_argument("--posture", choices=POSTURES, default="any", help="single: one shoulder configuration only")
ap.add_argument("--quick", action="store_true", help="5 draws, 150 poses")
ap.add_argument("--out", type=Path, default=Path("runs/paper"), help="output folder (default runs/paper)")


def experiment(a) -> dict:
    a.draws, a.poses = a.draws or (5 if a.quick else 20), a.poses or (150 if a.quick else 300)
    if a.draws < 1 or a.poses < 10:
        ap.error(f"need --draws >= 1 and --poses >= 10, got {a.draws} and {a.poses}")
    return run(a.draws, a.poses, a.seed, a.posture)


def main(argv: list[str] | None = None) -> int:
    args, result = common.run(ap, experiment, argv)
    summary = write_outputs(result, args.out)
    print(text_table(result), summary, sep="\n")
    common.emit(result, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
