"""Accuracy and speed of the geometric calibration on simulated UR5 campaigns; prints JSON.

For each seed: an 800-pose campaign with no effect beyond geometry (torchcal's simulator: biased DH,
unknown tracker pose and lever arm, 15 um tracker and 0.0005 deg joint noise), calibrated by
``torchcal.calibrate`` (default method) once with the file in metres and once in millimetres. The
reference is the error of the *true* model at the same held-out poses, i.e. the floor set by the
noise; the ratio ``rmse_after / floor`` is the figure of merit (1.0 = as good as knowing the truth).

    python scripts/bench_calibration.py [--seeds 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torchcal.calibrate import Options, calibrate, errors

import torchcal
from torchcal.sim import SimConfig, simulate, write_campaign


def one(seed: int, work: Path) -> dict:
    c = simulate(SimConfig(robot="ur5", poses=800, test_poses=200, seed=seed))
    write_campaign(c, work / f"s{seed}")
    t0 = time.perf_counter()
    run = calibrate("ur5", c.train, Options(seed=seed))
    seconds = time.perf_counter() - t0
    hold = c.train.subset(run.holdout_idx)
    floor = float(errors(c.model, hold, trajectory=False).square().mean().sqrt())
    # the same campaign through the command line in millimetres
    mm_dir = work / f"mm{seed}"
    subprocess.run([sys.executable, "-m", "torchcal", "simulate", "--robot", "ur5", "--out", str(mm_dir), "--seed",
                    str(seed), "--length-unit", "mm", "--quiet"], check=True)
    subprocess.run([sys.executable, "-m", "torchcal", "calibrate", str(mm_dir / "train.csv"), "--robot", "ur5",
                    "--out", str(work / f"run_mm{seed}"), "--length-unit", "mm", "--seed", str(seed), "--quiet"],
                   check=True)
    rep_mm = json.loads((work / f"run_mm{seed}" / "report.json").read_text())
    return {
        "seed": seed,
        "rmse_before_mm": run.stages[0].rmse * 1e3,
        "rmse_after_mm": run.stages[-1].rmse * 1e3,
        "floor_mm": floor * 1e3,
        "ratio_to_floor": run.stages[-1].rmse / floor,
        "rmse_after_mm_file_in_mm": rep_mm["rmse_after_mm"],
        "global_test": run.fits[-1].global_test["statistic"],
        "global_test_passed": run.fits[-1].global_test["passed"],
        "effects_added": len(run.effects_report),
        "seconds": seconds,
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory() as tmp:
        rows = [one(s, Path(tmp)) for s in range(100, 100 + args.seeds)]
    ratios = [r["ratio_to_floor"] for r in rows]
    out = {
        "torchcal": torchcal.__version__,
        "runs": rows,
        "ratio_to_floor_mean": statistics.mean(ratios),
        "ratio_to_floor_max": max(ratios),
        "mm_vs_m_max_rel_diff": max(abs(r["rmse_after_mm_file_in_mm"] / r["rmse_after_mm"] - 1) for r in rows),
        "seconds_max": max(r["seconds"] for r in rows),
        "false_effects": sum(r["effects_added"] for r in rows),
    }
    for r in rows:
        print(f"seed {r['seed']}: before {r['rmse_before_mm']:.4f} mm, after {r['rmse_after_mm']:.4f} mm, floor "
              f"{r['floor_mm']:.4f} mm (x{r['ratio_to_floor']:.3f}), global test {r['global_test']:.3f}, "
              f"{r['seconds']:.1f} s", file=sys.stderr)
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
