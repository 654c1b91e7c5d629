#!/usr/bin/env python3
"""Re-stationing after a 5 kg load and a 20 mm tool change (experiments.station_load, issues 45 and 46).

python scripts/station_load.py [--seeds 1,2] [--poses 200] [--points 10] [--shift-mm 12,-10,13]
    [--robot ur10] [--torques] [--json]
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, station_load

ap = common.parser(__doc__)
ap.add_argument("--seeds", default="1", help="comma-separated campaign seeds")
ap.add_argument("--poses", type=int, default=200, help="training poses of the run and of the fresh calibration")
ap.add_argument("--points", type=int, default=10, help="points of the new condition that re-station the run")
ap.add_argument("--robot", default="ur10", help="the simulated arm (arm7_dh: a DH table without link masses)")
ap.add_argument("--torques", action="store_true", help="every row carries measured joint torques (tau1..tauN)")
ap.add_argument("--shift-mm", default="12,-10,13", help="the tool change in the flange frame, x,y,z [mm]")


def main(argv=None) -> dict:
    args, out = common.run(
        ap,
        lambda a: station_load.run(
            tuple(int(s) for s in a.seeds.split(",")),
            a.poses,
            a.points,
            tuple(float(v) * 1e-3 for v in a.shift_mm.split(",")),
            a.robot,
            a.torques,
        ),
        argv,
    )
    common.emit(out, args, plain=out)
    return out


if __name__ == "__main__":
    main()
