"""Adaptive geometry in the integrated ANN-EKF (Horvath & Neuner 2024, Sec. 4 "future work"): geometry and network
estimated together on a simulated UR5 trajectory; see experiments.adaptive_geometry."""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.adaptive_geometry import run, table

ap = common.parser(__doc__)
ap.add_argument("--samples", type=int, default=7342)
ap.add_argument("--field", default="0.3mm", help="RMS of the non-geometric field at the probe, e.g. 0.15mm")
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--hidden", type=int, default=128, help="random features of the correction network")
ap.add_argument("--passes", type=int, default=1, help="filter passes (> 1: iterated, Gauss-Newton)")
ap.add_argument("--misfit-mm", type=float, default=0.0, help="std of the network's correlated misfit (0: none)")
ap.add_argument("--quick", action="store_true", help="2500 samples")


def experiment(a):
    a.samples = 2500 if a.quick else a.samples
    return run(a)


def main(argv=None) -> dict:
    args, result = common.run(ap, experiment, argv)
    print(table(result))
    common.emit(result, args, plain={k: v for k, v in result.items() if k != "rows"})
    return result


if __name__ == "__main__":
    main()
