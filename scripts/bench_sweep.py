#!/usr/bin/env python3
"""Wall time of an experiment's seed sweep on a local Ray against the same fits one after another, in one run:
``scripts/false_positives.py``'s clean simulated campaigns (``--seeds`` of ``--poses`` poses, the default method,
no trajectory campaign), first one after another in this process with one torch thread, then on a local Ray of
``--workers`` CPUs (its start and stop included); the ratio of the wall times and whether every row agrees.

    python scripts/bench_sweep.py --seeds 4 --workers 2 [--poses 400] [--json]
"""

import sys
import time

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.false_positives import run as false_positives
from torchcal import _console

ap = common.parser(__doc__)
ap.add_argument("--seeds", type=int, default=4, help="campaigns (default 4)")
ap.add_argument("--workers", type=int, default=2, help="CPUs of the local Ray instance (default 2)")
ap.add_argument("--poses", type=int, default=400, help="poses per campaign (default 400)")
ap.add_argument("--first-seed", type=int, default=1000)


def _rows(res: dict) -> list[dict]:
    """The sweep's rows without their wall times (which differ between runs)."""
    return [{k: v for k, v in r.items() if k != "seconds"} for r in res["rows"]]


def run(a) -> dict:
    _console.set_quiet(True)
    t0 = time.perf_counter()
    serial = false_positives("ur5", a.seeds, a.poses, 0, 0, a.first_seed, None)
    t_serial = time.perf_counter() - t0
    t0 = time.perf_counter()
    ray = false_positives("ur5", a.seeds, a.poses, 0, 0, a.first_seed, a.workers)
    t_ray = time.perf_counter() - t0
    return {
        "seeds": a.seeds,
        "poses": a.poses,
        "workers": a.workers,
        "serial_seconds": round(t_serial, 2),
        "ray_seconds": round(t_ray, 2),
        "ratio": round(t_ray / t_serial, 3),
        "identical": _rows(serial) == _rows(ray),
        "task_seconds_serial": [round(r["seconds"], 1) for r in serial["rows"]],
        "task_seconds_ray": [round(r["seconds"], 1) for r in ray["rows"]],
    }


def main(argv=None) -> dict:
    args, out = common.run(ap, run, argv)
    print(", ".join(f"{k} {v}" for k, v in out.items()), file=sys.stderr)
    common.emit(out, args)
    return out


if __name__ == "__main__":
    main()
