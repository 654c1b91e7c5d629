#!/usr/bin/env python3
"""Measure the learned stage alone (torchcal.experiments.learned_stage) and print the result as JSON.

Usage::

    python scripts/learned_stage.py --case harmonic3 --case field           # simulated UR5
    python scripts/learned_stage.py --case C --data ../shared/data/real/ur10-ipa
    python scripts/learned_stage.py --case A --data ../shared/data/real/ur10-ipa --methods geometry,gp
    python scripts/learned_stage.py --case synthetic-50000                   # time and memory at scale
"""

from __future__ import annotations

import argparse
import json

import torch

from torchcal._threads import torch_threads
from torchcal.effects.gp import GPSettings
from torchcal.experiments.learned_stage import real_case, scale_case, simulated_case


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", action="append", required=True, help="harmonic3, field, synthetic-N, or UR10 series A-D")
    ap.add_argument("--data", default="../shared/data/real/ur10-ipa", help="ur10-ipa directory (real series)")
    ap.add_argument("--methods", default="geometry,kernel,gp")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--additive", default="rbf", choices=("rbf", "periodic"))
    ap.add_argument("--max-inducing", type=int, default=GPSettings.max_inducing)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    methods = tuple(a.methods.split(","))
    s = GPSettings(additive=a.additive, max_inducing=a.max_inducing, seed=a.seed, threads=a.threads)
    out = []
    with torch_threads(a.threads):
        for case in a.case:
            if case.startswith("synthetic-"):
                out.append(scale_case(int(case.split("-", 1)[1]), a.seed, s))
            elif case in ("harmonic3", "field"):
                out.append(simulated_case(case, a.seed, methods=methods, gp_settings=s))
            else:
                out.append(real_case(a.data, case, a.seed, methods=methods, gp_settings=s))
    print(json.dumps({"torch_threads": torch.get_num_threads(), "results": out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
