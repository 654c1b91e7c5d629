"""Compensation closes the gap on the (simulated) robot: nominal commands vs geometry-only vs full-model compensation.

Calibrates a simulated UR5 campaign with undeclared effects, then commands fresh static targets and a
1000-target path and measures where the simulated true robot puts the probe. Prints JSON.

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 python scripts/compensation.py --seed 0
"""

from __future__ import annotations

import argparse
import json

from torchcal._threads import torch_threads
from torchcal.experiments.compensation import DEFAULT_EFFECTS, ExperimentConfig, run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="ur5")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--poses", type=int, default=800, help="calibration poses (plus 200 test poses)")
    ap.add_argument("--effect", action="append", default=None, help=f"simulated effect (default {DEFAULT_EFFECTS})")
    ap.add_argument("--static-targets", type=int, default=500)
    ap.add_argument("--path-targets", type=int, default=1000)
    ap.add_argument("--method", default=None, help="calibration method (default: the package default)")
    args = ap.parse_args()
    cfg = ExperimentConfig(
        robot=args.robot,
        seed=args.seed,
        poses=args.poses,
        effects=tuple(args.effect) if args.effect else DEFAULT_EFFECTS,
        static_targets=args.static_targets,
        path_targets=args.path_targets,
        method=args.method,
    )
    with torch_threads(1):
        print(json.dumps(run(cfg), indent=1))


if __name__ == "__main__":
    main()
