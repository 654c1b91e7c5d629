#!/usr/bin/env python3
"""The command line of :mod:`torchcal.experiments.adaptive_geometry`: adaptive geometry in the integrated ANN-EKF
(Horvath & Neuner 2024, Sec. 4 "future work"): geometry and network estimated together on a simulated, paper-like
UR5 trajectory.

The experiment and its outputs are described there; this script parses the arguments, runs it and prints.
"""

from __future__ import annotations

import argparse
import json

import torch

from torchcal.experiments import adaptive_geometry
from torchcal.experiments.adaptive_geometry import run, table


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=adaptive_geometry.__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=7342)
    ap.add_argument("--field", default="0.3mm", help="RMS of the non-geometric field at the probe, e.g. 0.15mm")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hidden", type=int, default=128, help="random features of the correction network")
    ap.add_argument("--passes", type=int, default=1, help="filter passes (> 1: iterated, Gauss-Newton)")
    ap.add_argument(
        "--misfit-mm",
        type=float,
        default=0.0,
        help="std of the network's correlated misfit (Gauss-Markov state, 50 samples); 0: none",
    )
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the filter's kernels are tiny)")
    ap.add_argument("--quick", action="store_true", help="2500 samples")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    args = ap.parse_args(argv)
    if args.quick:
        args.samples = 2500
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        result = run(args)
    finally:
        torch.set_num_threads(threads)
    print(table(result))
    print(json.dumps(result) if args.json else json.dumps({k: v for k, v in result.items() if k != "rows"}, indent=1))
    return result


if __name__ == "__main__":
    main()
