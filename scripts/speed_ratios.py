#!/usr/bin/env python3
"""Issue 49's speed ratios on real UR10 Series C, as CPU time of the commands in one run; prints JSON
(experiments.speed_ratios).

    python scripts/speed_ratios.py /path/to/ur10-ipa [--repeats 3] [--no-default] --json

``ratio_kinematic_vs_reference_plus_torch``: ``torchcal calibrate --method kinematic`` over the numpy reference
command plus ``python -c 'import torch'`` (target <= 2). ``ratio_default_vs_kinematic``: the default method's
command over the kinematic one (target <= 2.5). Each the shortest CPU time (user + sys of the child process) of
``--repeats`` alternating runs, one thread each.
"""

import tempfile
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.speed_ratios import measure

ap = common.parser(__doc__)
ap.add_argument("data_dir", type=Path, help="the ur10-ipa folder (holds Series_C)")
ap.add_argument("--repeats", type=int, default=3)
ap.add_argument("--series", default="C", help="which series (default C)")
ap.add_argument("--no-default", action="store_true", help="leave out the default method (the ratio (a) only)")


def experiment(a) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        return measure(a.data_dir, Path(tmp), a.repeats, a.series, default=not a.no_default)


if __name__ == "__main__":
    args, result = common.run(ap, experiment)
    common.emit(result, args, plain=result)
