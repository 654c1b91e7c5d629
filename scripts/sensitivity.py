#!/usr/bin/env python3
"""Reproduce the sensitivity analysis of Horvath & Neuner (2024), Sec. 3.3 and Fig. 13: how a bias in one parameter of
the filter's kinematic model moves the geometric part of the integrated ANN-EKF (experiments.sensitivity)."""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.sensitivity import run, text_table, write_outputs

ap = common.parser(__doc__)
ap.add_argument("--samples", type=int, default=3000, help="trajectory samples, 80 %% filtered (default 3000)")
ap.add_argument("--draws", type=int, default=1, help="noise draws per parameter (default 1)")
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--quick", action="store_true", help="500 samples, 1 draw")
ap.add_argument("--out", type=Path, default=Path("runs/paper"))


def main(argv: list[str] | None = None) -> int:
    args, result = common.run(ap, lambda a: run(*((500, a.seed, 1) if a.quick else (a.samples, a.seed, a.draws))), argv)
    print(write_outputs(result, args.out), file=sys.stderr)
    print(text_table(result))
    common.emit(result, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
