"""The integrated method against a random-feature ridge reference on multi-sine trajectories with a smooth field,
judged on each path's continuation (experiments.multisine_field; issue 50 item 4); prints JSON.

python scripts/multisine_field.py --seeds 0 1 2 3 4 5 6 7 8 9 --json
"""

import sys

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.multisine_field import table

ap = common.parser(__doc__)
ap.add_argument("--seeds", nargs="+", type=int, default=list(range(10)))
ap.add_argument("--field", default="0.2mm", help="RMS of the simulated field, with a unit")
ap.add_argument("--samples", type=int, default=7342)
ap.add_argument("--train-samples", type=int, default=5874)


def experiment(a):
    out = table(a.seeds, a.field, a.samples, a.train_samples)
    for r in out["rows"]:
        print(
            f"seed {r['seed']}: geometry {r['geometry_mm']:.4f}, integrated {r['integrated_mm']:.4f} "
            f"({r['chosen']}), ridge {r['ridge']['continuation_rmse_mm']:.4f} mm",
            file=sys.stderr,
        )
    return out


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
