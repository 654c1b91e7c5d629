#!/usr/bin/env python3
"""The command line of :mod:`experiments.plan_poses`: on a real UR10 series (ipa-robot-accuracy data), poses
chosen by ``torchcal plan`` from the series' training split against random ones, each calibrated (kinematic, or the
default method) and scored on the series' held-out poses, with the held-out error the plan predicted."""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common, plan_poses

ap = common.parser(plan_poses.__doc__.split("\n\n")[0])
ap.add_argument("data_dir", type=Path, nargs="?", help="the ur10-ipa folder (holds Series_A ... Series_D)")
ap.add_argument(
    "--simulated", default=None, help="a robot (ur5, ...): a simulated campaign instead of the real data (no data_dir)"
)
ap.add_argument("--series", default="A", help="series (default A)")
ap.add_argument("--k", default="30,100,500", help="design sizes, comma-separated (default 30,100,500)")
ap.add_argument(
    "--method",
    choices=("kinematic", "auto"),
    default="kinematic",
    help="the method each design is planned for and calibrated with (default kinematic; auto: the default method)",
)
ap.add_argument("--criterion", choices=("I", "D"), default="I", help="design criterion (default I)")
ap.add_argument(
    "--edge-share", type=float, default=None, help="share of picks at the region's edges (default: the method's design)"
)
ap.add_argument(
    "--spread-share",
    type=float,
    default=None,
    help="share of picks spreading the design (default: the method's design; 0: none)",
)
ap.add_argument(
    "--seeds", type=int, default=5, help="seeds per size: a planned design from a seeded half of the pool, a random one"
)
ap.add_argument(
    "--reference", type=int, default=200, help="random poses of the reference design (default 200; 0: none)"
)
ap.add_argument(
    "--sequential",
    type=int,
    default=0,
    help="instead: FIRST random poses calibrated with the default method, then K - FIRST planned with that run, "
    "once per --learned-shares value (one K)",
)
ap.add_argument(
    "--learned-shares", default="0,0.2", help="with --sequential: the learned correction's shares (default 0,0.2)"
)
ap.add_argument(
    "--oracle",
    action="store_true",
    help="per seed also a design whose spread picks follow the held-out poses themselves (what no planner knows)",
)
common.add_sweep_arguments(ap, "designs")


def experiment(a):
    if a.simulated is None and (a.data_dir is None or not a.data_dir.is_dir()):
        ap.error(f"data folder not found: {a.data_dir}")
    try:
        ks = tuple(int(v) for v in common.comma_list(ap, a.k, None, what="size"))
    except ValueError:
        ap.error(f"--k must be whole numbers separated by commas, got {a.k!r}")
    protocol = plan_poses.Protocol(
        ks=ks,
        seeds=a.seeds,
        reference=a.reference or None,
        edge_share=a.edge_share,
        criterion=a.criterion,
        spread_share=a.spread_share,
        method=a.method,
        oracle=a.oracle,
    )
    sweep = {"workers": a.workers, "address": a.address}
    if a.sequential:
        if a.simulated is not None or len(ks) != 1 or not 0 < a.sequential < ks[0]:
            ap.error("--sequential takes the real data and one --k above it")
        try:
            shares = tuple(float(v) for v in common.comma_list(ap, a.learned_shares, None, what="share"))
        except ValueError:
            ap.error(f"--learned-shares must be numbers separated by commas, got {a.learned_shares!r}")
        res = plan_poses.run_sequential(a.data_dir, a.series.upper(), a.sequential, ks[0], shares, a.seeds, **sweep)
        return res, plan_poses.sequential_markdown(res)
    if a.simulated is not None:
        res = plan_poses.simulated(a.simulated, protocol, **sweep)
    else:
        res = plan_poses.run(a.data_dir, a.series.upper(), protocol, **sweep)
    return res, plan_poses.markdown(res)


def main(argv=None) -> int:
    return common.run_markdown(ap, experiment, argv)


if __name__ == "__main__":
    sys.exit(main())
