"""The ``check-export`` command: an exported DH or URDF file loaded back and compared with its run."""

from __future__ import annotations

import argparse

from torchcal.cli._args import _add_common


def add_parser(sub: argparse._SubParsersAction) -> None:
    ce = sub.add_parser(
        "check-export",
        help="load an exported DH or URDF file back and compare it with its run",
        description="Load FILE (a DH YAML or URDF file written by torchcal export) as --robot loads it and print the "
        "largest difference of its chain to the run's exported chain (flange and probe, at the run's held-out joints) "
        "and the held-out RMSE of the file's chain with the run's instrument pose and lever arm.",
    )
    ce.add_argument("run", help="run directory written by calibrate (or station)")
    ce.add_argument("file", help="the exported file (.yaml, .yml or .urdf)")
    ce.add_argument(
        "--geometry",
        choices=("standalone", "cofitted"),
        default=None,
        help="compare with this chain of the run (default: whichever is closer to the file)",
    )
    _add_common(ce)


def handle(args) -> int:
    from torchcal.errors import OptionError
    from torchcal.use.export import MATCH_TOLERANCE_MM, check_export

    c = check_export(args.run, args.file, geometry=args.geometry)
    expected = "" if c.expected_mm is None else f" (the run recorded {c.expected_mm:.4f} mm for this chain)"
    chain = {"run": "own", "standalone": "stand-alone", "cofitted": "co-fitted"}[c.which]
    if not c.matches:  # a check a script can rely on: a file 391 mm from the run exited 0
        raise OptionError(
            f"{args.file} does not reproduce the run's {chain} chain: {c.fk_gap_mm:.4g} mm apart at the flange or "
            f"probe over {c.n} held-out poses (an export of {args.run} is within {MATCH_TOLERANCE_MM:g} mm); "
            f"held-out RMSE of the file's chain with the run's instrument pose and lever arm {c.rmse_mm:.4f} mm"
            f"{expected}"
        )
    print(
        f"{args.file} loaded to link '{c.tip}': largest difference to the run's {chain} chain {c.fk_gap_mm:.3g} mm "
        f"over {c.n} held-out poses; held-out RMSE with the run's instrument pose and lever arm "
        f"{c.rmse_mm:.4f} mm{expected}"
    )
    return 0
