#!/usr/bin/env python3
"""Held-out RMSE against the number of training poses (torchcal.experiments.learning_curve); prints JSON.

Usage::

    python scripts/learning_curve.py --data ../shared/data/real/ur10-ipa --series C,A --out runs/learning_curve
    python scripts/learning_curve.py --data ../shared/data/real/ur10-ipa --series A --sizes 50,100,200,500,1000
    python scripts/learning_curve.py --simulated 300 --sizes 50,100,all --out /tmp/lc   # a UR5 campaign, quick

Writes learning_curve.json, learning_curve.md (tables) and learning_curve.png into --out; the JSON object is
the last line of stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from torchcal._threads import torch_threads
from torchcal.data import read_ipa
from torchcal.experiments.ipa_series import series_file
from torchcal.experiments.learning_curve import (
    METHODS,
    SIZES,
    learning_curve,
    markdown,
    parse_sizes,
    plot,
    simulated_data,
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data/real/ur10-ipa"), help="the ur10-ipa folder")
    ap.add_argument("--series", default="C,A", help="UR10 series, comma separated (default C,A)")
    ap.add_argument("--simulated", type=int, default=0, help="a simulated UR5 campaign of this many poses instead")
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)), help="training sizes (integers and 'all')")
    ap.add_argument("--methods", default=",".join(METHODS), help="calibrate methods (default kinematic,auto)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("runs/learning_curve"))
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    a = ap.parse_args(argv)
    try:
        sizes = parse_sizes(a.sizes)
    except ValueError as err:
        ap.error(str(err))
    methods = tuple(m.strip() for m in a.methods.split(",") if m.strip())
    results = []
    with torch_threads(a.threads):
        if a.simulated:
            results.append(
                learning_curve(
                    "ur5", simulated_data(a.simulated, a.seed), sizes=sizes, methods=methods, seed=a.seed, name="sim"
                )
            )
        else:
            for s in (t.strip().upper() for t in a.series.split(",") if t.strip()):
                m = read_ipa(series_file(a.data, s))
                results.append(learning_curve("ur10", m, sizes=sizes, methods=methods, seed=a.seed, name=f"UR10 {s}"))
    a.out.mkdir(parents=True, exist_ok=True)
    out = {"threads": a.threads, "results": results}
    (a.out / "learning_curve.json").write_text(json.dumps(out, indent=1) + "\n")
    (a.out / "learning_curve.md").write_text(markdown(results))
    plot(results, a.out / "learning_curve.png")
    print(markdown(results))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
