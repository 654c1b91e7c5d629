#!/usr/bin/env python3
"""The command line of :mod:`torchcal.experiments.ur10_real`: calibrate the real UR10 (ipa-robot-accuracy data,
Leica tracker + T-Mac) and test across series.

The experiment and its outputs are described there; this script parses the arguments, runs it and prints.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from torchcal.experiments import ur10_real
from torchcal.experiments.ur10_real import (
    HOLDOUT,
    METHODS,
    MM,
    PAIRS,
    ROBOT,
    SEED,
    SERIES,
    load_series,
    markdown,
    source_calibration,
    transfer,
    within_series,
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=ur10_real.__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_A ... Series_D)")
    ap.add_argument("--out", type=Path, default=Path("runs/ur10"), help="output folder (default runs/ur10/)")
    ap.add_argument("--json", action="store_true", help="print the result as one JSON object on the last stdout line")
    ap.add_argument("--quick", action="store_true", help="series C, kinematic only, plus C -> B")
    ap.add_argument("--series", default=",".join(SERIES), help="series for part 1, comma separated (default A,B,C,D)")
    ap.add_argument("--methods", default=",".join(METHODS), help="methods for part 1 (default all)")
    ap.add_argument("--no-transfer", action="store_true", help="skip part 2 (across series)")
    ap.add_argument("--a-rows", type=int, default=0, help="subsample Series A to this many rows (default 0: all)")
    ap.add_argument(
        "--threads",
        type=int,
        default=0,
        help="torch CPU threads (default 0: torch's choice); 1 is steadier on a shared, busy machine",
    )
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if not args.data_dir.is_dir():
        ap.error(f"data folder not found: {args.data_dir}")

    t_start = time.perf_counter()
    if args.quick:
        names, methods, pairs = ("C",), ("kinematic",), (("C", "B"),)
    else:
        names = tuple(s.strip().upper() for s in args.series.split(",") if s.strip())
        bad = [s for s in names if s not in SERIES]
        if bad:
            ap.error(f"unknown series {', '.join(bad)}; valid: {', '.join(SERIES)}")
        methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
        if any(m not in METHODS for m in methods):
            ap.error(f"unknown method in {args.methods!r}; valid: {', '.join(METHODS)}")
        pairs = () if args.no_transfer else PAIRS
    needed = sorted(set(names) | {s for p in pairs for s in p})
    data, subsampled = load_series(args.data_dir, needed, args.a_rows)

    within = [within_series(s, data[s], meth) for s in names for meth in methods]
    self_cal = {r["series"]: r["final"] for r in within if r["method"] == "kinematic"}

    sources, runs, transfers = {}, {}, []
    for src, dst in pairs:
        if src not in runs:
            runs[src], dt = source_calibration(data[src])
            sources[src] = {"n_train": int(runs[src].train_idx.numel()), "runtime_s": dt}
        r = transfer(src, dst, runs[src], data[dst])
        r["source_lever_mm"] = [float(v) * MM for v in runs[src].model.robot.tool.vector().detach()]
        r["target_self"] = self_cal.get(dst)
        transfers.append(r)

    res = {
        "robot": ROBOT,
        "data_dir": str(args.data_dir),
        "seed": SEED,
        "holdout": HOLDOUT,
        "quick": args.quick,
        "threads": torch.get_num_threads(),
        "subsampled": subsampled,
        "within": within,
        "sources": sources,
        "transfer": transfers,
        "runtime_s": time.perf_counter() - t_start,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ur10_real.json").write_text(json.dumps(res, indent=2) + "\n")
    md = markdown(res)
    (args.out / "ur10_real.md").write_text(md)
    print(md)
    if args.json:
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
