#!/usr/bin/env python3
"""Reproduce Table 2 of Horvath & Neuner (2024): the kinematic calibration with the paper's fixed parameters.

The experiment is torchcal.experiments.table2; this prints the table (``--json``: and the result as one JSON
object on the last line) and writes table2.json and table2.md into ``--out``.
"""

import sys
from pathlib import Path

from torchcal.experiments import common
from torchcal.experiments.table1 import POSTURES
from torchcal.experiments.table2 import run, text_table, write_outputs

ap = common.parser(__doc__)
ap.add_argument("--draws", type=int, default=None, help="Monte Carlo draws per variant (default 20, quick 3)")
ap.add_argument("--poses", type=int, default=None, help="calibration poses (default 300, quick 150)")
ap.add_argument("--test-poses", type=int, default=None, help="held-out poses (default 100, quick 50)")
ap.add_argument("--seed", type=int, default=0, help="seed of the poses, tracker, lever arm and biases")
ap.add_argument("--posture", choices=POSTURES, default="any", help="single: one shoulder configuration only")
ap.add_argument("--quick", action="store_true", help="3 draws, 150 poses, 50 held out")
ap.add_argument("--out", type=Path, default=Path("runs/paper"), help="output folder (default runs/paper)")


def experiment(a) -> dict:
    a.draws, a.poses = a.draws or (3 if a.quick else 20), a.poses or (150 if a.quick else 300)
    a.test_poses = a.test_poses or (50 if a.quick else 100)
    if a.draws < 1 or a.poses < 60 or a.test_poses < 1:
        ap.error(f"need --draws >= 1, --poses >= 60, --test-poses >= 1, got {a.draws}, {a.poses}, {a.test_poses}")
    return run(a.draws, a.poses, a.test_poses, a.seed, a.posture)


def main(argv: list[str] | None = None) -> int:
    args, result = common.run(ap, experiment, argv)
    summary = write_outputs(result, args.out)
    print(text_table(result), summary, sep="\n")
    common.emit(result, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
