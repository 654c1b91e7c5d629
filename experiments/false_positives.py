"""False-positive rate of the closed loop: clean simulated campaigns (geometry only) over many seeds
(``scripts/false_positives.py``).

Each campaign is calibrated with the default ``auto`` method (geometric fit, the closed loop, then
the learned stage). A false positive is a run that names any effect (a named effect or the
learned residual model) although the simulation injected none; every candidate of the closed loop's menu is
covered, the couplings between every pair of joints among them (``by_kind`` counts the runs that named each
kind). Reported: the rate with its exact
(Clopper-Pearson) 95 % upper bound, how often a named effect reached the validation stage, and the
held-out error of the final model against the geometric fit (clean data: no worse).
"""

from __future__ import annotations

import math
import statistics
import sys
import time

from experiments.closed_loop import run_cases
from torchcal._version import __version__

#: the kinds a false positive is counted by (``by_kind``): the closed loop's named kinds and the learned residual
FP_KINDS = ("compliance", "backlash", "cyclic", "transmission", "coupling", "drift", "instrument", "learned")


def binom_cdf(k: int, n: int, p: float) -> float:
    return sum(math.comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(k + 1))


def clopper_pearson_upper(k: int, n: int, level: float = 0.95) -> float:
    """Exact one-sided upper confidence bound of a binomial rate with ``k`` events in ``n`` trials."""
    if k >= n:
        return 1.0
    lo, hi = k / n, 1.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if binom_cdf(k, n, mid) > 1 - level else (lo, mid)
    return hi


def summarise(rows: list[dict]) -> dict:
    n = len(rows)
    named = [r for r in rows if any(f[0] != "learned" for f in r["found"])]
    any_effect = [r for r in rows if r["found"]]
    worse = [r for r in rows if r["loop_mm"] > r["geometric_mm"] * (1 + 1e-9)]
    return {
        "runs": n,
        "false_positive_runs": len(any_effect),
        "false_positive_rate": len(any_effect) / n if n else float("nan"),
        "false_positive_rate_upper95": clopper_pearson_upper(len(any_effect), n) if n else float("nan"),
        "named_effect_runs": len(named),
        "named_effect_rate": len(named) / n if n else float("nan"),
        "named_effect_rate_upper95": clopper_pearson_upper(len(named), n) if n else float("nan"),
        "runs_where_a_candidate_reached_validation": sum(1 for r in rows if any(x != "learned" for x in r["rejected"])),
        "by_kind": {k: sum(1 for r in rows if any(f[0] == k for f in r["found"])) for k in FP_KINDS},
        "runs_where_a_coupling_reached_validation": sum(
            1 for r in rows if any(x.startswith("coupling") for x in r["rejected"])
        ),
        "runs_worse_than_geometric": len(worse),
        "max_ratio_to_geometric": max(r["loop_mm"] / r["geometric_mm"] for r in rows) if rows else float("nan"),
        "seconds_median": statistics.median(r["seconds"] for r in rows) if rows else float("nan"),
        "seconds_max": max(r["seconds"] for r in rows) if rows else float("nan"),
        "false_positives": [
            {"seed": r["seed"], "trajectory": r["trajectory"], "found": r["found"]} for r in any_effect
        ],
    }


def _progress_line(r: dict) -> str:
    """The line shown on stderr when the run ``r`` ends."""
    return (
        f"seed {r['seed']}{' (trajectory)' if r['trajectory'] else ''}: found {r['found'] or 'nothing'}, "
        f"geometric {r['geometric_mm']:.4f} mm, final {r['loop_mm']:.4f} mm, {r['seconds']:.1f} s"
    )


def run(
    robot: str,
    seeds: int,
    poses: int,
    trajectories: int,
    samples: int,
    first_seed: int,
    workers: int | None = None,
    address: str | None = None,
    load: dict | None = None,
    stations: int = 1,
) -> dict:
    """Calibrate ``seeds`` static campaigns of ``poses`` poses and ``trajectories`` trajectory campaigns of
    ``samples`` samples, all clean, on ``workers`` Ray CPUs or the cluster at ``address``
    (:func:`~experiments.closed_loop.run_cases`; default one after another); each run is shown on stderr as it
    ends. ``load`` (``payload_levels``, ``torques``) gives the static campaigns load columns, so that the closed loop
    offers its load candidates (clean still: the truth has no compliance; the payload moves nothing); ``stations``
    places the static campaigns' instrument that many times, so that the closed loop offers the instrument's own
    error terms.

    Returns:
        The summaries (all, static, trajectory) and the rows of every run.
    """
    cases = [
        {"robot": robot, "poses": poses, "seed": first_seed + i, "load": load, "stations": stations}
        for i in range(seeds)
    ]
    cases += [
        {"robot": robot, "trajectory": True, "samples": samples, "seed": first_seed + 5000 + i}
        for i in range(trajectories)
    ]
    t0 = time.perf_counter()

    rows = run_cases(cases, workers, lambda r: print(_progress_line(r), file=sys.stderr), address)
    static = [r for r in rows if not r["trajectory"]]
    traj = [r for r in rows if r["trajectory"]]
    out = {
        "torchcal": __version__,
        "robot": robot,
        "poses": poses,
        "samples": samples,
        "load": load,
        "stations": stations,
        "all": summarise(rows),
        "static": summarise(static),
        "trajectory": summarise(traj),
        "wall_seconds": time.perf_counter() - t0,
        "rows": rows,
    }
    a = out["all"]
    print(
        f"{a['runs']} clean campaigns: {a['false_positive_runs']} named something "
        f"(rate {a['false_positive_rate']:.3f}, 95 % upper bound {a['false_positive_rate_upper95']:.3f}); "
        f"named effects {a['named_effect_runs']}; worse than geometric {a['runs_worse_than_geometric']}",
        file=sys.stderr,
    )
    return out
