#!/usr/bin/env python3
"""Detection limits of the closed loop: per effect family, the smallest size it names reliably.

For every family and size, ``--seeds`` simulated campaigns (800 poses by default, 15 um tracker
noise) each get one effect of that family on a joint drawn from the family's joints (seeded), and
are calibrated with the default ``auto`` method. A run *detects* the effect when the report names
exactly the injected (kind, joint) and nothing else. The detection limit of a family is the
smallest size from which on every larger size in the grid is detected in at least ``--reliable``
of the runs (default 0.9). SIZE is the RMS displacement of the probe the effect causes (as
``torchcal simulate --effect`` defines it).

    python scripts/detection_limits.py [--seeds 10] [--sizes 5,7.5,10,15,20,30] [--workers 2] [--json]
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time

import torch

import torchcal
from torchcal import _console
from torchcal.experiments.closed_loop import run_cases

#: joints per family on a UR arm where the effect moves the probe in a way geometry cannot absorb
#: (joint 1's gravity torque is zero: its compliance and backlash are a constant offset; joint 6
#: carries no gravity torque with the probe on its axis)
FAMILIES = {
    "compliance": [2, 3, 4, 5],
    "backlash": [2, 3, 4, 5],
    "cyclic": [1, 2, 3, 4, 5, 6],
    "drift:t": [None],
    "drift:temperature": [None],
}


def spec(family: str, joint: int | None, size_um: float) -> str:
    return f"{family}{'' if joint is None else f':{joint}'}={size_um:g}um"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="ur5")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--sizes", default="5,7.5,10,15,20,30", help="sizes in um RMS (default 5,7.5,10,15,20,30)")
    ap.add_argument("--seeds", type=int, default=10, help="campaigns per family and size (default 10)")
    ap.add_argument("--poses", type=int, default=800)
    ap.add_argument("--reliable", type=float, default=0.9, help="detection rate that counts as reliable")
    ap.add_argument("--first-seed", type=int, default=2000)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    args = ap.parse_args(argv)
    _console.set_quiet(True)
    if args.workers <= 1:
        torch.set_num_threads(1)
    families = args.families.split(",")
    sizes = [float(s) for s in args.sizes.split(",")]
    cases, keys = [], []
    for fam in families:
        rng = random.Random(f"{fam}-{args.first_seed}")
        for size in sizes:
            for i in range(args.seeds):
                joint = rng.choice(FAMILIES[fam])
                cases.append(
                    {
                        "robot": args.robot,
                        "effects": [spec(fam, joint, size)],
                        "poses": args.poses,
                        "seed": args.first_seed + i,
                    }
                )
                keys.append((fam, size))
    t0 = time.perf_counter()

    def show(r):
        print(
            f"{r['effects'][0]:28s} seed {r['seed']}: found {r['found'] or 'nothing'} "
            f"({'ok' if r['correct'] else 'MISS'}), {r['seconds']:.1f} s",
            file=sys.stderr,
        )

    rows = run_cases(cases, args.workers, show)
    table = {}
    for (fam, size), r in zip(keys, rows):
        t = table.setdefault(fam, {}).setdefault(size, {"runs": 0, "detected": 0, "wrong": [], "ratio_true_form": []})
        t["runs"] += 1
        t["detected"] += int(r["correct"])
        if not r["correct"]:
            t["wrong"].append({"effect": r["effects"][0], "seed": r["seed"], "found": r["found"]})
        if r["true_form_mm"]:
            t["ratio_true_form"].append(r["loop_mm"] / r["true_form_mm"])
    limits = {}
    for fam, by_size in table.items():
        limit = None
        for size in sorted(by_size, reverse=True):
            if by_size[size]["detected"] / by_size[size]["runs"] >= args.reliable:
                limit = size
            else:
                break
        limits[fam] = limit
        for size in sorted(by_size):
            t = by_size[size]
            t["rate"] = t["detected"] / t["runs"]
            t["ratio_true_form_max"] = max(t["ratio_true_form"]) if t["ratio_true_form"] else None
            print(
                f"{fam:18s} {size:5g} um: detected {t['detected']}/{t['runs']}, held-out RMSE / true form max "
                f"{t['ratio_true_form_max']:.3f}",
                file=sys.stderr,
            )
        print(f"{fam:18s} detection limit: {limit} um", file=sys.stderr)
    out = {
        "torchcal": torchcal.__version__,
        "robot": args.robot,
        "poses": args.poses,
        "seeds": args.seeds,
        "reliable": args.reliable,
        "limits_um": limits,
        "table": {f: {str(s): v for s, v in t.items()} for f, t in table.items()},
        "wall_seconds": time.perf_counter() - t0,
    }
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
