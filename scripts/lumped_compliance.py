#!/usr/bin/env python3
"""Compliance of a DH-only 7-axis arm without link masses (experiments.lumped_compliance, issue 25).

python scripts/lumped_compliance.py [--seeds 5] [--poses 215] [--effects compliance:2=60um,compliance:4=40um] [--json]
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, lumped_compliance

ap = common.parser(__doc__)
ap.add_argument("--seeds", type=int, default=5)
ap.add_argument("--first-seed", type=int, default=1)
ap.add_argument("--poses", type=int, default=215)
ap.add_argument("--effects", default="compliance:2=60um,compliance:4=40um")


def main(argv=None) -> dict:
    args, out = common.run(
        ap,
        lambda a: lumped_compliance.run(a.seeds, a.first_seed, a.effects.split(","), a.poses),
        argv,
    )
    common.emit(out, args, plain={k: v for k, v in out.items() if k != "rows"})
    return out


if __name__ == "__main__":
    main()
