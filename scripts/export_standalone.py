#!/usr/bin/env python3
"""The command line of :mod:`experiments.export_standalone`: the DH and URDF exports of a default-method run, loaded
alone and re-registered on the training rows, against the kinematic run's, on held-out rows. Prints one JSON line."""

from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, export_standalone

ap = common.parser(export_standalone.__doc__.split("\n\n")[0])
ap.add_argument("folders", nargs="*", type=Path, help="campaign folders with train.csv and test.csv")
ap.add_argument("--robot", default="ur5", help="the campaigns' robot (default ur5: the outside campaigns)")
ap.add_argument("--ipa", type=Path, default=None, help="the ur10-ipa folder (holds Series_A ... Series_D)")
ap.add_argument("--series", default="", help="ipa series to measure, e.g. B,C,D (needs --ipa)")


def experiment(a):
    for f in a.folders:
        if not (f / "train.csv").is_file() or not (f / "test.csv").is_file():
            ap.error(f"{f}: expected a folder with train.csv and test.csv")
    series = tuple(s.strip().upper() for s in a.series.split(",") if s.strip())
    if series and (a.ipa is None or not a.ipa.is_dir()):
        ap.error("--series needs --ipa, the ur10-ipa folder")
    return export_standalone.run(list(a.folders), a.robot, a.ipa, series)


def main(argv=None) -> int:
    args, result = common.run(ap, experiment, argv)
    print(__import__("json").dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
