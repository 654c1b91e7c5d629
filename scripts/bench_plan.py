#!/usr/bin/env python3
"""Wall time of ``torchcal plan`` against a baseline source tree, in one run: each case runs as a command (the import
included, as a user waits for it) with this tree's torchcal and with the baseline's, alternating, one torch thread
each, and the planned poses of both are compared. Cases: ``--n`` poses from ``--pool`` sampled candidates of
``--robot``; ``--large N`` also times this tree alone on N sampled candidates (the baseline did not finish 100,000).

The baseline is a torchcal source tree, e.g. the commit before the speed-up:

    git archive 6305d8e torchcal robots | tar -x -C /tmp/plan-base
    python scripts/bench_plan.py --baseline /tmp/plan-base [--n 100,500] [--pool 10000] [--large 100000] [--json]
"""

import os
import sys
import tempfile
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common

HERE = Path(__file__).resolve().parents[1]

ap = common.parser(__doc__)
ap.add_argument("--baseline", default=None, help="a torchcal source tree to compare with (none: this tree alone)")
ap.add_argument("--robot", default="ur5")
ap.add_argument("--n", default="100,500", help="poses to plan, comma-separated, one case each")
ap.add_argument("--pool", type=int, default=10_000, help="sampled candidates (default 10000, plan's default)")
ap.add_argument("--large", type=int, default=0, help="also plan --n 100 of this many candidates (this tree only)")


def plan_once(tree: Path, out: Path, n: int, pool: int, robot: str) -> tuple[float, float]:
    """Wall and CPU seconds of one ``torchcal plan`` with ``tree``'s torchcal (the CPU time counts beside other
    work, where the wall time counts the others too); raises where it fails."""
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torchcal", "plan", "--robot", robot, "--n", str(n), "--pool", str(pool)]
    # run in the tree: ``python -m`` puts the working directory first on the path
    argv = [*cmd, "--out", str(out), "--quiet", "--force"]
    return common.timed_command(argv, env=env, cwd=tree, what=f"{tree}: plan --n {n}")


def case(base: Path | None, tmp: Path, n: int, pool: int, robot: str) -> dict:
    """One case: this tree's time, the baseline's, the ratio and whether the poses agree."""
    ours = plan_once(HERE, tmp / f"ours_{n}.csv", n, pool, robot)
    out = {"n": n, "pool": pool, "seconds": round(ours[0], 2), "cpu_seconds": round(ours[1], 2)}
    if base is not None:
        theirs = plan_once(base, tmp / f"base_{n}.csv", n, pool, robot)
        same = (tmp / f"ours_{n}.csv").read_text() == (tmp / f"base_{n}.csv").read_text()
        out.update(
            baseline_seconds=round(theirs[0], 2),
            baseline_cpu_seconds=round(theirs[1], 2),
            ratio=round(ours[0] / theirs[0], 3),
            cpu_ratio=round(ours[1] / theirs[1], 3),
            same_poses=same,
        )
    return out


def run(args) -> dict:
    base = None if args.baseline is None else Path(args.baseline).resolve()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cases = [case(base, tmp, int(n), args.pool, args.robot) for n in common.comma_list(ap, args.n)]
        if args.large:
            cases.append(case(None, tmp, 100, args.large, args.robot))
    return {"robot": args.robot, "baseline": str(base), "cases": cases}


def main(argv=None) -> dict:
    args, out = common.run(ap, run, argv)
    for c in out["cases"]:
        print(", ".join(f"{k} {v}" for k, v in c.items()), file=sys.stderr)
    common.emit(out, args)
    return out


if __name__ == "__main__":
    main()
