#!/usr/bin/env python3
"""Reproduce Table 2 of Horvath & Neuner (2024): the command line of :mod:`torchcal.experiments.table2`.

The experiment, its set-up and its outputs are described there; this script parses the arguments, runs it and
prints the table (``--json``: and the result as one JSON object on the last line).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchcal._threads import torch_threads
from torchcal.experiments import table2
from torchcal.experiments.common import add_common_arguments, emit_json
from torchcal.experiments.table1 import POSTURES
from torchcal.experiments.table2 import *  # noqa: F403 (the experiment's names, for the tests and for users)
from torchcal.experiments.table2 import run, text_table, write_outputs


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        description=table2.__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    ap.add_argument("--draws", type=int, default=None, help="Monte Carlo draws per variant (default 20, quick 3)")
    ap.add_argument("--poses", type=int, default=None, help="calibration poses (default 300, quick 150)")
    ap.add_argument("--test-poses", type=int, default=None, help="held-out poses (default 100, quick 50)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the poses, tracker, lever arm and biases")
    ap.add_argument(
        "--posture",
        choices=POSTURES,
        default="any",
        help="any: every visible pose (default); single: one shoulder configuration only",
    )
    ap.add_argument("--quick", action="store_true", help="3 draws, 150 poses, 50 held out")
    add_common_arguments(ap)
    ap.add_argument("--out", type=Path, default=Path("runs/paper"), help="output folder (default runs/paper)")
    args = ap.parse_args(argv)
    args.draws = args.draws or (3 if args.quick else 20)
    args.poses = args.poses or (150 if args.quick else 300)
    args.test_poses = args.test_poses or (50 if args.quick else 100)
    if args.draws < 1 or args.poses < 60 or args.test_poses < 1:
        ap.error(
            f"need --draws >= 1, --poses >= 60 and --test-poses >= 1, got {args.draws}, {args.poses} and "
            f"{args.test_poses}"
        )
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with torch_threads(args.threads):
        result = run(args.draws, args.poses, args.test_poses, args.seed, args.posture)
    write_outputs(result, args.out)
    print(text_table(result))
    print(f"fixed: {', '.join(result['fixed_parameters'])}; {result['runtime_s']:.1f} s; written to {args.out}")
    emit_json(result, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
