#!/usr/bin/env python3
"""Couplings on a plain UR5: the default method names ``joint j picks up c x joint k`` and reaches 1.2 x the true
model's held-out error; clean campaigns name none (experiments.couplings).

    python scripts/couplings.py [--full] [--clean 2] [--poses 800] [--seed 500] [--workers 2] [--json]

Without --full: each adjacent pair once (downstream joint from upstream, shares 2e-4, 6e-4, 2e-3 in turn) and two
clean campaigns, a few minutes on one core; --full: every adjacent pair both ways x the three shares, and --clean 20.
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, couplings
from torchcal import _console

ap = common.parser(__doc__)
ap.add_argument("--full", action="store_true", help="the full grid: 10 directed adjacent pairs x 3 shares")
ap.add_argument("--clean", type=int, default=None, help="clean campaigns (default 2, 20 with --full)")
ap.add_argument("--poses", type=int, default=800, help="training poses per campaign (default 800)")
ap.add_argument("--seed", type=int, default=500, help="first seed (default 500)")
common.add_sweep_arguments(ap, "campaigns")


def main(argv=None) -> dict:
    _console.set_quiet(True)

    def experiment(a):
        clean = a.clean if a.clean is not None else (20 if a.full else 2)
        return couplings.run(a.full, a.seed, clean, a.poses, a.workers, a.address)

    args, out = common.run(ap, experiment, argv)
    common.emit(out, args, plain={k: v for k, v in out.items() if k != "rows"})
    return out


if __name__ == "__main__":
    main()
