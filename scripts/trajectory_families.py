"""The integrated method on trajectory families, judged on the continuation of each path (JSON).

python scripts/trajectory_families.py --paths p2p multisine randomwalk sweeps --seeds 0 1
python scripts/trajectory_families.py --outside ../shared/data/outside/trajectory-ann-s31
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.trajectories import family_table, outside_campaign
from torchcal.sim import PATHS

ap = common.parser(__doc__)
ap.add_argument("--paths", nargs="+", default=list(PATHS), choices=PATHS)
ap.add_argument("--seeds", nargs="+", type=int, default=[0])
ap.add_argument("--field", default="0.2mm", help="RMS of the simulated field, with a unit")
ap.add_argument("--engines", nargs="+", default=["auto"], choices=("auto", "adaptive", "ekf"))
ap.add_argument("--outside", nargs="*", default=[], help="outside trajectory campaign folders (train.csv, test.csv)")


def experiment(a):
    if a.outside:
        return [outside_campaign(f, a.engines) for f in a.outside]
    return family_table(a.paths, a.seeds, a.field, engines=a.engines)


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
