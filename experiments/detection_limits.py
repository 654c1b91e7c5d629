"""Detection limits of the closed loop: per effect family, the smallest size it names reliably
(``scripts/detection_limits.py``).

For every family and size, ``seeds`` simulated campaigns (800 poses by default, 15 um tracker
noise) each get one effect of that family on a joint drawn from the family's joints (seeded), and
are calibrated with the default ``auto`` method. A run *detects* the effect when the report names
exactly the injected (kind, joint) and nothing else. The detection limit of a family is the
smallest size from which on every larger size in the grid is detected in at least ``reliable``
of the runs (default 0.9). SIZE is the RMS displacement of the probe the effect causes (as
``torchcal simulate --effect`` defines it).
"""

from __future__ import annotations

import random
import sys
import time

from experiments.closed_loop import run_cases
from torchcal._version import __version__

#: joints per family on a UR arm where the effect moves the probe in a way geometry cannot absorb
#: (joint 1's gravity torque is zero: its compliance and backlash are a constant offset; joint 6
#: carries no gravity torque with the probe on its axis)
FAMILIES = {
    "compliance": [2, 3, 4, 5],
    "backlash": [2, 3, 4, 5],
    "cyclic": [1, 2, 3, 4, 5, 6],
    "drift:t": [None],
    "drift:temperature": [None],
}


def spec(family: str, joint: int | None, size_um: float) -> str:
    return f"{family}{'' if joint is None else f':{joint}'}={size_um:g}um"


def _progress_line(r: dict) -> str:
    """The line shown on stderr when the run ``r`` ends."""
    return (
        f"{r['effects'][0]:28s} seed {r['seed']}: found {r['found'] or 'nothing'} "
        f"({'ok' if r['correct'] else 'MISS'}), {r['seconds']:.1f} s"
    )


def run(
    robot: str,
    families: list[str],
    sizes: list[float],
    seeds: int,
    poses: int,
    reliable: float,
    first_seed: int,
    workers: int | None = None,
    address: str | None = None,
) -> dict:
    """Calibrate ``seeds`` campaigns per family and size [um RMS] on ``workers`` Ray CPUs or the cluster at
    ``address`` (:func:`~experiments.closed_loop.run_cases`; default one after another); each run and each family's
    table are shown on stderr.

    Returns:
        The detection limit per family [um] (None: not reliable at any size of the grid) and the table.
    """
    cases, keys = [], []
    for fam in families:
        rng = random.Random(f"{fam}-{first_seed}")
        for size in sizes:
            for i in range(seeds):
                joint = rng.choice(FAMILIES[fam])
                cases.append(
                    {
                        "robot": robot,
                        "effects": [spec(fam, joint, size)],
                        "poses": poses,
                        "seed": first_seed + i,
                    }
                )
                keys.append((fam, size))
    t0 = time.perf_counter()

    rows = run_cases(cases, workers, lambda r: print(_progress_line(r), file=sys.stderr), address)
    table = {}
    for (fam, size), r in zip(keys, rows):
        t = table.setdefault(fam, {}).setdefault(size, {"runs": 0, "detected": 0, "wrong": [], "ratio_true_form": []})
        t["runs"] += 1
        t["detected"] += int(r["correct"])
        if not r["correct"]:
            t["wrong"].append({"effect": r["effects"][0], "seed": r["seed"], "found": r["found"]})
        if r["true_form_mm"]:
            t["ratio_true_form"].append(r["loop_mm"] / r["true_form_mm"])
    limits = {}
    for fam, by_size in table.items():
        limit = None
        for size in sorted(by_size, reverse=True):
            if by_size[size]["detected"] / by_size[size]["runs"] >= reliable:
                limit = size
            else:
                break
        limits[fam] = limit
        for size in sorted(by_size):
            t = by_size[size]
            t["rate"] = t["detected"] / t["runs"]
            t["ratio_true_form_max"] = max(t["ratio_true_form"]) if t["ratio_true_form"] else None
            print(
                f"{fam:18s} {size:5g} um: detected {t['detected']}/{t['runs']}, held-out RMSE / true form max "
                f"{t['ratio_true_form_max']:.3f}",
                file=sys.stderr,
            )
        print(f"{fam:18s} detection limit: {limit} um", file=sys.stderr)
    out = {
        "torchcal": __version__,
        "robot": robot,
        "poses": poses,
        "seeds": seeds,
        "reliable": reliable,
        "limits_um": limits,
        "table": {f: {str(s): v for s, v in t.items()} for f, t in table.items()},
        "wall_seconds": time.perf_counter() - t0,
    }
    return out
