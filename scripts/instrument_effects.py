#!/usr/bin/env python3
"""The instrument's own errors on a plain UR5 re-stationed twice: the default method names the tracker's error term
(and an encoder's harmonic) and reaches 1.2 x the true model's held-out error; clean campaigns name none
(experiments.instrument_effects).

    python scripts/instrument_effects.py [--full | --cases tracker_az:3=40urad,range_offset=50um] [--clean 2]
        [--poses 800] [--stations 3] [--seed 700] [--workers 2] [--json]

Without --full or --cases: the quick grid (azimuth harmonics 1, 4, 8 and elevation 2, 6 over 20-60 urad, a range
offset and scale, each tilt, a beam offset) and two clean campaigns; --full: harmonics 1-8 of either encoder at 20,
40, 60 urad, two sizes of every other term, and --clean 20.
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, instrument_effects
from torchcal import _console

ap = common.parser(__doc__)
ap.add_argument("--full", action="store_true", help="the full grid (58 terms)")
ap.add_argument("--cases", default=None, help="comma-separated simulate --effect specs instead of a grid")
ap.add_argument("--clean", type=int, default=None, help="clean campaigns (default 2, 20 with --full)")
ap.add_argument("--poses", type=int, default=800, help="training poses per campaign (default 800)")
ap.add_argument("--stations", type=int, default=3, help="instrument placements per campaign (default 3)")
ap.add_argument("--seed", type=int, default=700, help="first seed (default 700)")
common.add_sweep_arguments(ap, "campaigns")


def main(argv=None) -> dict:
    _console.set_quiet(True)

    def experiment(a):
        clean = a.clean if a.clean is not None else (20 if a.full else 2)
        names = [c.strip() for c in a.cases.split(",") if c.strip()] if a.cases else None
        return instrument_effects.run(a.full, a.seed, clean, a.poses, a.stations, names, a.workers, a.address)

    args, out = common.run(ap, experiment, argv)
    common.emit(out, args, plain={k: v for k, v in out.items() if k != "rows"})
    return out


if __name__ == "__main__":
    main()
