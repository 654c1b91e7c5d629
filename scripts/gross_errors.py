"""Gross errors in a simulated campaign: found, named, and the held-out error on a clean test file.

    python scripts/gross_errors.py                      # 5 % of 800 rows shifted by 10 mm, seed 0, kinematic
    python scripts/gross_errors.py --mode mm --count 5  # five rows in millimetres among rows in metres
    python scripts/gross_errors.py --count 1 --where holdout --seeds 0 1 2

Prints one JSON object per seed (:func:`torchcal.experiments.gross_errors.gross_error_trial`): the test-file
RMSE of the clean and of the contaminated calibration and their ratio, found and false-rejection rates, and
the rejected file lines.
"""

from __future__ import annotations

import argparse
import json

from torchcal._threads import torch_threads
from torchcal.experiments.gross_errors import MODES, gross_error_trial


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="campaign seeds (default 0)")
    ap.add_argument("--mode", choices=MODES, default="shift", help="shift rows by --size, or write them in mm")
    ap.add_argument("--fraction", type=float, default=0.05, help="share of the rows to contaminate (default 0.05)")
    ap.add_argument("--count", type=int, default=None, help="number of rows to contaminate (overrides --fraction)")
    ap.add_argument("--size-mm", type=float, default=10.0, help="shift in mm (default 10)")
    ap.add_argument(
        "--where",
        choices=("all", "training", "holdout"),
        default="all",
        help="contaminate any row, or only training or held-out rows of the calibration's split",
    )
    ap.add_argument("--method", default="kinematic", help="calibration method (default kinematic)")
    ap.add_argument("--poses", type=int, default=800, help="training-file poses (default 800)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = ap.parse_args(argv)
    with torch_threads(args.threads):
        for seed in args.seeds:
            r = gross_error_trial(
                seed,
                mode=args.mode,
                fraction=args.fraction,
                count=args.count,
                size=args.size_mm * 1e-3,
                where=args.where,
                method=args.method,
                poses=args.poses,
            )
            print(json.dumps(r), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
