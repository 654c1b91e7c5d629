#!/usr/bin/env python3
"""The command line of :mod:`torchcal.experiments.ur10_investigate`: what remains on the real UR10 after the
geometric fit (issue 5, item 5): noise, configuration, reach, drift.

The experiment and its outputs are described there; this script parses the arguments, runs it and prints.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from torchcal.experiments import ur10_investigate
from torchcal.experiments.ipa_series import series_file
from torchcal.experiments.ur10_investigate import ROBOT, SEED, SERIES, _clean, investigate, summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=ur10_investigate.__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_A ... Series_D)")
    ap.add_argument("--series", default=",".join(SERIES), help="comma separated (default A,B,C,D)")
    ap.add_argument("--json", action="store_true", help="print the result as one JSON object on the last stdout line")
    ap.add_argument("--a-rows", type=int, default=3000, help="Series A: fit on this many seeded rows (0: all)")
    ap.add_argument("--pair-rows", type=int, default=3000, help="rows for the correlation curves (seeded subsample)")
    ap.add_argument("--tol", type=float, default=1e-3, help="revisit: every joint within this [rad] (default 1e-3)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if not args.data_dir.is_dir():
        ap.error(f"data folder not found: {args.data_dir}")
    names = tuple(s.strip().upper() for s in args.series.split(",") if s.strip())
    bad = [s for s in names if s not in SERIES]
    if bad:
        ap.error(f"unknown series {', '.join(bad)}; valid: {', '.join(SERIES)}")

    t0 = time.perf_counter()
    out = [investigate(s, series_file(args.data_dir, s), args.a_rows, args.pair_rows, args.tol) for s in names]
    res = _clean(
        {
            "robot": ROBOT,
            "data_dir": str(args.data_dir),
            "seed": SEED,
            "tol_rad": args.tol,
            "threads": torch.get_num_threads(),
            "series": out,
            "runtime_s": time.perf_counter() - t0,
        }
    )
    print(summary(res), file=sys.stderr)
    if args.json:
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
