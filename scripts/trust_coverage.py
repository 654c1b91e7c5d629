#!/usr/bin/env python3
"""Coverage of predict's sx, sy, sz on real held-out rows (experiments.trust_coverage); prints JSON.

    python scripts/trust_coverage.py ../shared/data/real/ur10-ipa --series C --split grouped --json
    python scripts/trust_coverage.py ../shared/data/real/ur10-ipa --series C --split q2-central --json

``grouped``: a seeded 20 % of the revisit groups held out; ``q2-central``: trained on the central 70 % of q2's range,
tested on the rest. Printed: the share of test rows whose three |error| / sigma are all <= 3, the median
|error| / sigma, the RMSE and the median sigma, and the same for the sigma of the parameters alone. ``--probes``:
instead, the default method and the kinematic calibration of the whole series probed 0.1-0.6 rad beyond one joint's
range: their sigmas there, the largest difference of their predictions, and the probes predict gives to the
kinematic calibration.
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, trust_coverage

ap = common.parser(__doc__)
ap.add_argument("data", type=Path, help="the ur10-ipa data set (the folder holding Series_A ... Series_D)")
ap.add_argument("--series", default="C", help="the series (default C)")
ap.add_argument("--split", choices=trust_coverage.SPLITS, default="grouped")
ap.add_argument("--method", default="auto", help="calibration method (default auto)")
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--probes", action="store_true", help="probe both models beyond the data instead of a split")


def experiment(a):
    if not a.data.is_dir():
        ap.error(f"data folder not found: {a.data}")
    if a.probes:
        return trust_coverage.probe_check(a.data, a.series, seed=a.seed)
    return trust_coverage.run(a.data, a.series, a.split, seed=a.seed, method=a.method)


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
    sys.exit(0)
