"""Accuracy and speed of the geometric calibration on simulated UR5 campaigns (``scripts/bench_calibration.py``).

For each seed: an 800-pose campaign with no effect beyond geometry (torchcal's simulator: biased DH,
unknown tracker pose and lever arm, 15 um tracker and 0.0005 deg joint noise), calibrated by
``torchcal.calibrate`` (default method) once with the file in metres and once in millimetres. The
reference is the error of the *true* model at the same held-out poses, i.e. the floor set by the
noise; the ratio ``rmse_after / floor`` is the figure of merit (1.0 = as good as knowing the truth).

:func:`compare` instead times one calibration of DATA per method
(default: ``auto``, then ``kinematic``) in a fresh process with one torch thread, stage by stage (import, robot, read,
fit, report: wall and CPU seconds, peak resident memory after each; ``parts``: the nested stages of the default
method -- screening, closed loop with its score tests, localisation and refits, learned stage with its kernel, GP and
network fits, all least-squares fits), and with ``--load`` every run again while a busy Python process holds one core;
``summary`` gives each method's wall time, its ratio to the last method's and the loaded/quiet ratio. A part's CPU time
is the whole process's while it ran: the learned stage fits its GP in a second thread beside the network and the kernel
regression, so those parts also count the GP's CPU time, and the GP posterior's row blocks run on two threads.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from torchcal._version import __version__
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate
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
    subprocess.run(
        [
            sys.executable,
            "-m",
            "torchcal",
            "simulate",
            "--robot",
            "ur5",
            "--out",
            str(mm_dir),
            "--seed",
            str(seed),
            "--length-unit",
            "mm",
            "--quiet",
        ],
        check=True,
    )
    subprocess.run(
        [
            sys.executable,
            "-m",
            "torchcal",
            "calibrate",
            str(mm_dir / "train.csv"),
            "--robot",
            "ur5",
            "--out",
            str(work / f"run_mm{seed}"),
            "--length-unit",
            "mm",
            "--seed",
            str(seed),
            "--quiet",
        ],
        check=True,
    )
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


_STAGES = r"""
import functools, json, resource, sys, time
def now():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return time.perf_counter(), r.ru_utime + r.ru_stime, r.ru_maxrss / 1024
out, last, parts = [], now(), {}
def mark(name):
    global last
    t = now()
    out.append({"stage": name, "wall_s": t[0] - last[0], "cpu_s": t[1] - last[1], "peak_mb": t[2]})
    last = t
def timed(module, attr, name):
    # wrap module.attr so that its calls add up under parts[name] (wall, CPU, calls, peak memory after them)
    fn = getattr(module, attr)
    @functools.wraps(fn)
    def wrapper(*a, **k):
        t0 = now()
        try:
            return fn(*a, **k)
        finally:
            t1 = now()
            e = parts.setdefault(name, {"calls": 0, "wall_s": 0.0, "cpu_s": 0.0, "peak_mb": 0.0})
            e["calls"] += 1
            e["wall_s"] += t1[0] - t0[0]
            e["cpu_s"] += t1[1] - t0[1]
            e["peak_mb"] = t1[2]
    setattr(module, attr, wrapper)
import torch
from torchcal import pipeline as C
from torchcal.data import read_measurements
from torchcal.report import write_run
from torchcal.robot import load_robot
from torchcal.pipeline import loop as L, learned as LS, run as R
from torchcal.estimate import fit as EF
mark("import")
# the default method's stages (nested: the loop's refits are inside "closed loop", the learned stage's inside it)
for mod, attr, name in [
    (R, "screen_gross_errors", "screening"),
    (R, "close_loop", "closed loop"),
    (L, "score_candidates", "closed loop: score tests"),
    (L, "localise_fit", "closed loop: localisation"),
    (L, "open_candidates", "closed loop: open forms"),
    (L, "_validate", "closed loop: validation refits"),
    (L, "_accept", "closed loop: accepted refits"),
    (L, "unexplained_entries", "closed loop: unexplained"),
    (R, "learned_stage", "learned stage"),
    (LS, "select_learned", "learned: selection"),
    (LS, "refine_learned", "learned: alternating refits"),
    (LS, "prune_named", "learned: pruning named effects"),
    (LS, "fit_kernel_correction", "learned: kernel fits"),
    (LS, "fit_gp_correction", "learned: GP fits"),
    (LS, "fit_net", "learned: network fits"),
    (EF, "levenberg_marquardt", "least squares of estimate.fit.solve"),
]:
    if hasattr(mod, attr):
        timed(mod, attr, name)
data_path, spec, method, out_dir = sys.argv[1:5]
robot = load_robot(spec)
mark("robot")
data = read_measurements(data_path, dof=robot.dof, require_positions=True)
mark("read")
run = C.calibrate(robot, data, C.Options(method=method), robot_spec=spec)
mark("fit")
write_run(run, out_dir)
mark("report")
print(json.dumps({
    "stages": out,
    "parts": parts,
    "rmse_holdout_mm": run.stages[-1].rmse * 1e3,
    "rmse_geometric_mm": next(s.rmse for s in run.stages if s.name == "geometric") * 1e3,
    "effects": [e.name for e in run.effects],
}))
"""


def stages(data: str, robot: str, method: str, work: Path) -> dict:
    """One calibration in a fresh process (one torch thread), timed stage by stage; ``parts`` times the default
    method's nested stages (closed loop, its score tests and refits, the learned stage, every least-squares fit)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", _STAGES, data, robot, method, str(work / "run")],
        check=True,
        capture_output=True,
        text=True,
        env=env,
    )
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["total_wall_s"] = time.perf_counter() - t0
    out["peak_mb"] = max(s["peak_mb"] for s in out["stages"])
    return out


def busy_process() -> subprocess.Popen:
    """A competing process: one core's worth of a pure-Python busy loop."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def compare(data: str, robot: str, methods: list[str], load: bool, work: Path) -> dict:
    """Each method quiet, then (with ``load``) each again beside a busy process; ratios to the first method."""
    res: dict = {"data": data, "robot": robot, "methods": methods, "quiet": {}, "loaded": {}}
    for m in methods:
        res["quiet"][m] = stages(data, robot, m, work / f"q-{m.replace('+', '_')}")
    if load:
        busy = busy_process()
        try:
            for m in methods:
                res["loaded"][m] = stages(data, robot, m, work / f"l-{m.replace('+', '_')}")
        finally:
            busy.kill()
            busy.wait()
    ref = methods[-1]
    res["summary"] = {
        m: {
            "quiet_wall_s": res["quiet"][m]["total_wall_s"],
            "quiet_peak_mb": res["quiet"][m]["peak_mb"],
            "quiet_ratio_to_" + ref: res["quiet"][m]["total_wall_s"] / res["quiet"][ref]["total_wall_s"],
            **(
                {
                    "loaded_wall_s": res["loaded"][m]["total_wall_s"],
                    "loaded_over_quiet": res["loaded"][m]["total_wall_s"] / res["quiet"][m]["total_wall_s"],
                }
                if load
                else {}
            ),
            "rmse_holdout_mm": res["quiet"][m]["rmse_holdout_mm"],
            "effects": res["quiet"][m]["effects"],
        }
        for m in methods
    }
    return res


def accuracy(seeds: int) -> dict:
    """Calibrate the campaigns of seeds 100 .. 100 + ``seeds`` - 1 with :func:`one`; each run is shown on stderr.

    Returns:
        The runs and their summary (ratio to the noise floor, metres against millimetres, seconds, false effects).
    """
    with tempfile.TemporaryDirectory() as tmp:
        rows = [one(s, Path(tmp)) for s in range(100, 100 + seeds)]
    ratios = [r["ratio_to_floor"] for r in rows]
    out = {
        "torchcal": __version__,
        "runs": rows,
        "ratio_to_floor_mean": statistics.mean(ratios),
        "ratio_to_floor_max": max(ratios),
        "mm_vs_m_max_rel_diff": max(abs(r["rmse_after_mm_file_in_mm"] / r["rmse_after_mm"] - 1) for r in rows),
        "seconds_max": max(r["seconds"] for r in rows),
        "false_effects": sum(r["effects_added"] for r in rows),
    }
    for r in rows:
        print(
            f"seed {r['seed']}: before {r['rmse_before_mm']:.4f} mm, after {r['rmse_after_mm']:.4f} mm, floor "
            f"{r['floor_mm']:.4f} mm (x{r['ratio_to_floor']:.3f}), global test {r['global_test']:.3f}, "
            f"{r['seconds']:.1f} s",
            file=sys.stderr,
        )
    return out
