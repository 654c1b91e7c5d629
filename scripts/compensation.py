"""Compensation closes the gap on the (simulated) robot: nominal commands vs geometry-only vs full-model compensation.

Calibrates a simulated UR5 campaign with undeclared effects, then commands fresh static targets and a
1000-target path and measures where the simulated true robot puts the probe. Prints JSON.

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 python scripts/compensation.py --seed 0
    PYTHONPATH=$PWD OMP_NUM_THREADS=1 python scripts/compensation.py --seed 0 --orientation 0.01   # 6-D probe
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.compensation import DEFAULT_EFFECTS, ExperimentConfig, run

ap = common.parser(__doc__)
ap.add_argument("--robot", default="ur5")
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--poses", type=int, default=800, help="calibration poses (plus 200 test poses)")
ap.add_argument("--effect", action="append", default=None, help=f"simulated effect (default {DEFAULT_EFFECTS})")
ap.add_argument("--static-targets", type=int, default=500)
ap.add_argument("--path-targets", type=int, default=1000)
ap.add_argument("--method", default=None, help="calibration method (default: the package default)")
ap.add_argument(
    "--orientation",
    type=float,
    default=None,
    metavar="DEG",
    help="a 6-D probe with this orientation noise [deg]: also compensate position and orientation together and report "
    "the true robot's orientation error beside its position error (six_d: the ratios to position-only)",
)
ap.add_argument(
    "--orientation-weight",
    type=float,
    default=0.1,
    metavar="M_PER_RAD",
    help="with --orientation: how much an orientation error weighs against a position error in the 6-D solve [m/rad] "
    "(compensate's orientation_weight, default 0.1)",
)


def experiment(a):
    effects = tuple(a.effect) if a.effect else DEFAULT_EFFECTS
    kw = {k: getattr(a, k) for k in ("robot", "seed", "poses", "static_targets", "path_targets", "method")}
    return run(
        ExperimentConfig(effects=effects, orientation_deg=a.orientation, orientation_weight=a.orientation_weight, **kw)
    )


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
