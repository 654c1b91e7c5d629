#!/usr/bin/env python3
"""Wall time of ``torchcal fleet`` on a local Ray against the same calibrations one after another, in one run:
``--robots`` simulated UR5 campaigns (seeds 1..R, ``--poses`` each), one manifest, the fleet run first one after
another in this process (``engine="serial"``), then on a local Ray of ``--workers`` CPUs (its start included); the
ratio of the wall times and whether every robot's report numbers agree.

    python scripts/bench_fleet.py --robots 8 --workers 2 [--poses 200] [--method auto] [--json]
"""

import sys
import tempfile
import time
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from torchcal import fleet as F
from torchcal.cli import main as cli

ap = common.parser(__doc__)
ap.add_argument("--robots", type=int, default=8)
ap.add_argument("--workers", type=int, default=2)
ap.add_argument("--poses", type=int, default=200, help="training poses per simulated robot (default 200)")
ap.add_argument("--method", default="auto", choices=F.METHODS)


def _campaigns(root: Path, robots: int, poses: int, method: str) -> Path:
    """Simulate the robots' campaigns under ``root`` and write their manifest."""
    rows = ["name,data,robot,method"]
    for s in range(1, robots + 1):
        code = cli(
            ["simulate", "--robot", "ur5", "--out", str(root / f"sim{s}"), "--poses", str(poses)]
            + ["--test-poses", "10", "--seed", str(s), "--quiet"]
        )
        if code != 0:
            raise RuntimeError(f"simulate seed {s} exited {code}")
        rows.append(f"robot{s},sim{s}/train.csv,ur5,{method}")
    manifest = root / "manifest.csv"
    manifest.write_text("\n".join(rows) + "\n")
    return manifest


def run(args) -> dict:
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        manifest = _campaigns(root, args.robots, args.poses, args.method)
        t0 = time.perf_counter()
        serial = F.run_fleet(manifest, root / "serial", engine="serial")
        t_serial = time.perf_counter() - t0
        t0 = time.perf_counter()
        ray = F.run_fleet(manifest, root / "ray", engine="ray", workers=args.workers)
        t_ray = time.perf_counter() - t0
    numbers = [{r["name"]: (r["status"], r.get("report")) for r in f.to_dict()["robots"]} for f in (serial, ray)]
    return {
        "robots": args.robots,
        "workers": args.workers,
        "poses": args.poses,
        "method": args.method,
        "serial_seconds": round(t_serial, 2),
        "ray_seconds": round(t_ray, 2),
        "ratio": round(t_ray / t_serial, 3),
        "identical": numbers[0] == numbers[1],
        "n_ok": serial.to_dict()["n_ok"],
    }


def main(argv=None) -> dict:
    args, out = common.run(ap, run, argv)
    print(", ".join(f"{k} {v}" for k, v in out.items()), file=sys.stderr)
    common.emit(out, args)
    return out


if __name__ == "__main__":
    main()
