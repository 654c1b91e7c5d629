"""Gross errors in a simulated campaign: found, named, and the held-out error on a clean test file.

    python scripts/gross_errors.py                      # 5 % of 800 rows shifted by 10 mm, seed 0, kinematic
    python scripts/gross_errors.py --mode mm --count 5  # five rows in millimetres among rows in metres
    python scripts/gross_errors.py --count 1 --where holdout --seeds 0 1 2

Prints one JSON object per seed as it finishes (experiments.gross_errors.gross_error_trial): the test-file
RMSE of the clean and of the contaminated calibration and their ratio, found and false-rejection rates, and the
rejected file lines; ``--json`` adds ``{"trials": [...]}`` as the last line.
"""

import json

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.gross_errors import MODES, gross_error_trial

ap = common.parser(__doc__)
ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="campaign seeds (default 0)")
ap.add_argument("--mode", choices=MODES, default="shift", help="shift rows by --size, or write them in mm")
ap.add_argument("--fraction", type=float, default=0.05, help="share of the rows to contaminate (default 0.05)")
ap.add_argument("--count", type=int, default=None, help="number of rows to contaminate (overrides --fraction)")
ap.add_argument("--size-mm", type=float, default=10.0, help="shift in mm (default 10)")
ap.add_argument("--where", choices=("all", "training", "holdout"), default="all", help="rows of the split to spoil")
ap.add_argument("--method", default="kinematic", help="calibration method (default kinematic)")
ap.add_argument("--poses", type=int, default=800, help="training-file poses (default 800)")


def experiment(a) -> dict:
    kw = {k: getattr(a, k) for k in ("mode", "fraction", "count", "where", "method", "poses")}
    trials = []
    for seed in a.seeds:
        trials.append(gross_error_trial(seed, size=a.size_mm * 1e-3, **kw))
        print(json.dumps(trials[-1]), flush=True)
    return {"trials": trials}


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args)
