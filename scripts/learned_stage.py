"""Measure the learned stage alone (experiments.learned_stage) and print the result as JSON.

python scripts/learned_stage.py --case harmonic3 --case field           # simulated UR5
python scripts/learned_stage.py --case C --data ../shared/data/real/ur10-ipa
python scripts/learned_stage.py --case A --data ../shared/data/real/ur10-ipa --methods geometry,gp
python scripts/learned_stage.py --case synthetic-50000                   # time and memory at scale
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.learned_stage import run_cases
from torchcal.effects.gp import GPSettings

ap = common.parser(__doc__)
ap.add_argument("--case", action="append", required=True, help="harmonic3, field, synthetic-N, or UR10 series A-D")
ap.add_argument("--data", default="../shared/data/real/ur10-ipa", help="ur10-ipa directory (real series)")
ap.add_argument("--methods", default="geometry,kernel,gp")
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--additive", default="rbf", choices=("rbf", "periodic"))
ap.add_argument("--max-inducing", type=int, default=GPSettings.max_inducing)


def experiment(a):
    s = GPSettings(additive=a.additive, max_inducing=a.max_inducing, seed=a.seed, threads=a.threads)
    return run_cases(a.case, a.data, a.seed, tuple(a.methods.split(",")), s)


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
