"""The integrated method on trajectory families, judged on the continuation of each path (JSON).

python scripts/trajectory_families.py --paths p2p multisine randomwalk sweeps --seeds 0 1
python scripts/trajectory_families.py --outside ../shared/data/outside/trajectory-ann-s31
"""

import argparse
import json

from torchcal.experiments.trajectories import family_table, outside_campaign
from torchcal.sim import PATHS

p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
p.add_argument("--paths", nargs="+", default=list(PATHS), choices=PATHS)
p.add_argument("--seeds", nargs="+", type=int, default=[0])
p.add_argument("--field", default="0.2mm", help="RMS of the simulated field, with a unit")
p.add_argument("--engines", nargs="+", default=["auto"], choices=("auto", "adaptive", "ekf"))
p.add_argument("--outside", nargs="*", default=[], help="outside trajectory campaign folders (train.csv, test.csv)")
a = p.parse_args()
if a.outside:
    print(json.dumps([outside_campaign(f, a.engines) for f in a.outside], indent=1))
else:
    print(json.dumps(family_table(a.paths, a.seeds, a.field, engines=a.engines), indent=1))
