#!/usr/bin/env python3
"""Forward-kinematics agreement of every built-in robot: torchcal against an independent numpy standard DH and
against pytorch-kinematics (experiments.fk_agreement); prints JSON.

    python scripts/fk_agreement.py [--poses 1000]
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.fk_agreement import agreement

ap = common.parser(__doc__)
ap.add_argument("--poses", type=int, default=1000)

if __name__ == "__main__":
    args, result = common.run(ap, lambda a: agreement(a.poses))
    common.emit(result, args, plain=result)
