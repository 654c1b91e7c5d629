#!/usr/bin/env python3
"""The command line of :mod:`torchcal.experiments.sensitivity`: reproduce the sensitivity analysis of Horvath &
Neuner (2024), Sec. 3.3 and Fig. 13: how a bias in one parameter of the filter's kinematic model moves the geometric
part of the integrated ANN-EKF.

The experiment and its outputs are described there; this script parses the arguments, runs it and prints.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from torchcal._threads import torch_threads
from torchcal.experiments import sensitivity
from torchcal.experiments.sensitivity import PAPER_LARGEST, plot, run, text_table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=sensitivity.__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=3000, help="trajectory samples, 80 %% filtered (default 3000)")
    ap.add_argument("--draws", type=int, default=1, help="noise draws per parameter (default 1)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="500 samples, 1 draw")
    ap.add_argument("--out", default="runs/paper")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last stdout line")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = ap.parse_args(argv)
    if args.quick:
        args.samples, args.draws = 500, 1
    with torch_threads(args.threads):
        result = run(args.samples, args.seed, args.draws)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "sensitivity.json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, out / "fig13_sensitivity.png")
    print(text_table(result))
    print(
        f"largest DH influences here: {', '.join(result['ranking_dh'][:5])}; paper: {', '.join(PAPER_LARGEST)}; "
        f"exactness check {result['check_max_abs_diff_m']:.1e} m; {result['seconds']:.1f} s",
        file=sys.stderr,
    )
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
