"""The ``fleet`` command: one calibration per manifest line, in parallel on Ray."""

from __future__ import annotations

from pathlib import Path

from torchcal import _console
from torchcal.cli._args import OUT_REPLACED, _add_common, _count
from torchcal.errors import OptionError


def add_parser(sub) -> None:
    fl = sub.add_parser(
        "fleet",
        help="calibrate a fleet: one calibration (or re-check from a prior run) per manifest line, in parallel on Ray",
        description="Run one calibration per line of MANIFEST (a CSV with the columns name,data,robot and optionally "
        "method,prior; paths relative to its folder) as independent tasks on Ray (pip install torchcal[fleet]; "
        "without it the tasks run one after another): line NAME's run in OUT/NAME/, a summary of every robot's "
        "held-out error, what moved since its prior and which need a new calibration in OUT/report.json and "
        "report.md. A failed task is reported as its line's and the others go on.",
    )
    fl.add_argument("manifest", help="CSV: name,data,robot[,method][,prior], a header row first")
    fl.add_argument("--out", required=True, help="fleet directory to write. " + OUT_REPLACED)
    fl.add_argument("--workers", type=_count, default=None, help="CPUs of the local Ray instance (default: all)")
    fl.add_argument(
        "--address",
        default=None,
        help="an existing Ray cluster instead of a private local instance: HOST:PORT, the head's address as "
        "'ray start --head' prints it (port 6379 by default); auto, the cluster started on this machine; or "
        "ray://HOST:10001, the head's Ray Client server where it runs one. A head with token authentication needs "
        "RAY_AUTH_MODE=token and its token (RAY_AUTH_TOKEN or ~/.ray/auth_token) in this environment",
    )
    _add_common(fl)


def handle(args) -> int:
    from torchcal.fleet import print_progress, ray_available, run_fleet

    if args.address and args.workers:
        raise OptionError("--workers sizes a local Ray instance; a cluster at --address has its own")
    if not ray_available():
        _console.info(
            "torchcal fleet: Ray is not installed (pip install torchcal[fleet]): the calibrations run one after another"
        )
    fleet = run_fleet(args.manifest, args.out, workers=args.workers, address=args.address, progress=print_progress)
    d = fleet.to_dict()
    _console.info(
        f"{d['n_ok']} of {d['n_lines']} calibrated ({d['engine']}, {d['seconds']:.1f} s); needs a new calibration: "
        f"{', '.join(d['needs_calibration']) or 'none'}; wrote {Path(args.out) / 'report.json'}"
    )
    return 0
