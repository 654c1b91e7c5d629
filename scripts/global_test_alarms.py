#!/usr/bin/env python3
"""False alarms of the global test's unit/description hint on plain campaigns (experiments.global_test_alarms).

python scripts/global_test_alarms.py [--ipa PATH/TO/ur10-ipa] [--series A,B,C,D] [--outside PATH/TO/outside]
    [--method kinematic] [--mistakes] [--json]

--mistakes: instead, a simulated campaign with its joints or positions in another unit (experiments.global_test_alarms
.mistakes): each must be refused or read as a mistake.
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.global_test_alarms import mistakes, run
from torchcal import _console

ap = common.parser(__doc__)
ap.add_argument("--ipa", default=None, help="the ipa-robot-accuracy folder (Series_A ... Series_D)")
ap.add_argument(
    "--series",
    type=lambda t: common.comma_list(ap, t, ("A", "B", "C", "D"), what="series", upper=True),
    default=("A", "B", "C", "D"),
)
ap.add_argument("--outside", default=None, help="the outside campaigns' folder (index.json)")
ap.add_argument("--method", default="kinematic", help="calibration method (default kinematic)")
ap.add_argument("--mistakes", action="store_true", help="the unit mistakes on a simulated campaign instead")


def main(argv=None) -> dict:
    _console.set_quiet(True)
    args, out = common.run(
        ap, lambda a: mistakes(a.method) if a.mistakes else run(a.ipa, a.series, a.outside, a.method), argv
    )
    common.emit(out, args, plain=out)
    return out


if __name__ == "__main__":
    main()
