#!/usr/bin/env python3
"""Robots that are not UR-like: a linear track, a lifting column with a mimic segment, a parallelogram robot fed its
controller readings and a 7-axis arm with a wrist differential and no masses (experiments.any_robot).

python scripts/any_robot.py [--cases track,column,parallelogram,arm7_differential] [--seeds 1,2] [--poses 300] [--json]
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import any_robot, common

ap = common.parser(__doc__)
ap.add_argument("--cases", default=",".join(any_robot.CASES))
ap.add_argument("--seeds", default="1")
ap.add_argument("--poses", type=int, default=300)
ap.add_argument("--no-clean", action="store_true", help="leave out the clean campaigns")


def main(argv=None) -> dict:
    args, out = common.run(
        ap,
        lambda a: any_robot.run(
            a.cases.split(","), [int(s) for s in a.seeds.split(",")], a.poses, clean=not a.no_clean
        ),
        argv,
    )
    common.emit(out, args, plain={k: v for k, v in out.items() if k != "rows"})
    return out


if __name__ == "__main__":
    main()
