#!/usr/bin/env python3
"""The command line of :mod:`experiments.export_as_robot`: a run's own export as ``--robot`` for a new calibration
of the same rows, and whether the new run's sigma covers the test rows. Prints one JSON line.

    python scripts/export_as_robot.py PATH/TO/outside/jointscale-s404 [--method auto] [--formats dh,urdf] --json
"""

from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, export_as_robot

ap = common.parser(__doc__)
ap.add_argument("folders", nargs="+", type=Path, help="campaign folders with train.csv and test.csv")
ap.add_argument("--robot", default="ur5", help="the campaigns' robot (default ur5: the outside campaigns)")
ap.add_argument("--method", default="auto", help="calibration method of both runs (default auto)")
ap.add_argument("--formats", default="dh", help="export formats to calibrate again with: dh, urdf (comma-separated)")


def experiment(a):
    for f in a.folders:
        if not (f / "train.csv").is_file() or not (f / "test.csv").is_file():
            ap.error(f"{f}: expected a folder with train.csv and test.csv")
    formats = tuple(s.strip() for s in a.formats.split(",") if s.strip())
    if not formats or any(s not in ("dh", "urdf") for s in formats):
        ap.error(f"--formats must name dh and/or urdf, got {a.formats!r}")
    return export_as_robot.run(list(a.folders), a.robot, a.method, formats)


def main(argv=None) -> dict:
    args, result = common.run(ap, experiment, argv)
    common.emit(result, args, plain=result)
    return result


if __name__ == "__main__":
    main()
