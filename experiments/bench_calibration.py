"""Accuracy and speed of the geometric calibration on simulated UR5 campaigns (``scripts/bench_calibration.py``).

For each seed: an 800-pose campaign with no effect beyond geometry (torchcal's simulator: biased DH,
unknown tracker pose and lever arm, 15 um tracker and 0.0005 deg joint noise), calibrated by
``torchcal.calibrate`` (default method) once with the file in metres and once in millimetres. The
reference is the error of the *true* model at the same held-out poses, i.e. the floor set by the
noise; the ratio ``rmse_after / floor`` is the figure of merit (1.0 = as good as knowing the truth).

:func:`compare` instead times one calibration of DATA per method (default: ``auto``, then ``kinematic``) in a fresh
process with one torch thread, through the memory probe of :mod:`~experiments.bench_memory`, stage by stage
(import, robot, read, fit, report: wall and CPU seconds, each stage's own peak resident memory; ``parts``: the nested
stages of the fit -- screening, closed loop with its score tests, localisation and refits, learned stage with its
kernel, GP and network fits, every LM fit), and with ``--load`` every run again while a busy Python process holds one
core; ``summary`` gives each method's wall time, its ratio to the last method's and the loaded/quiet ratio. A part's
CPU time is the whole process's while it ran: the learned stage fits its GP in a second thread beside the network and
the kernel regression, so those parts also count the GP's CPU time.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments import bench_memory
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


#: the default method's nested stages the probe times besides its own (:data:`~experiments._memprobe.TARGETS`:
#: screening, closed loop, learned stage, every LM fit as ``LM``), as ``MODULE:ATTR=NAME``
PARTS = [
    "torchcal.pipeline.loop:score_candidates=closed loop: score tests",
    "torchcal.pipeline.loop:localise_fit=closed loop: localisation",
    "torchcal.pipeline.loop:open_candidates=closed loop: open forms",
    "torchcal.pipeline.loop:_validate=closed loop: validation refits",
    "torchcal.pipeline.loop:_accept=closed loop: accepted refits",
    "torchcal.pipeline.loop:unexplained_entries=closed loop: unexplained",
    "torchcal.pipeline.learned:select_learned=learned: selection",
    "torchcal.pipeline.learned:refine_learned=learned: alternating refits",
    "torchcal.pipeline.learned:prune_named=learned: pruning named effects",
    "torchcal.pipeline.learned:fit_kernel_correction=learned: kernel fits",
    "torchcal.pipeline.learned:fit_gp_correction=learned: GP fits",
    "torchcal.pipeline.learned:fit_net=learned: network fits",
]
#: the top-level stages of one run and the probe's stages each sums
_TOP = {"robot": "command/robot", "read": "command/read", "fit": "command/fit", "report": "command/report"}


def stages(data: str, robot: str, method: str, work: Path, *, parts: list[str] = PARTS) -> dict:
    """One ``torchcal calibrate`` in a fresh process (one torch thread) through the memory probe
    (:func:`~experiments.bench_memory.calibration`), stage by stage: ``stages`` import, robot, read, fit and
    report (wall and CPU seconds, each one's own peak resident memory), ``parts`` every stage inside the fit by name
    (the closed loop, its score tests and refits, the learned stage and its fits, every LM fit; summed where a name
    comes at several depths) and inside the report, and the run's held-out errors and effects from its report.json.
    ``parts``: the nested stages to time besides the probe's own (default :data:`PARTS`)."""
    out_dir = work / "run"
    res = bench_memory.calibration(data, robot, method, out_dir, targets=parts)
    recs = res["stages"]

    def total(rows: list[dict]) -> dict:
        return {
            "calls": sum(r["calls"] for r in rows),
            "wall_s": sum(r["wall_s"] for r in rows),
            "cpu_s": sum(r["cpu_s"] for r in rows),
            "peak_mb": max((r["peak_mb"] for r in rows), default=0.0),
        }

    top = [{"stage": "import", **total([r for r in recs if r["stage"].startswith("command/import ")])}]
    top += [{"stage": name, **total([r for r in recs if r["stage"] == path])} for name, path in _TOP.items()]
    inner = [r for r in recs if r["stage"].startswith(("command/fit/", "command/report/"))]
    leaf = {r["stage"]: r["stage"].rsplit("/", 1)[1] for r in inner}
    parts = {name: total([r for r in inner if leaf[r["stage"]] == name]) for name in dict.fromkeys(leaf.values())}
    report = json.loads((out_dir / "report.json").read_text())
    return {
        "stages": top,
        "parts": parts,
        "rmse_holdout_mm": report["rmse_after_mm"],
        "rmse_geometric_mm": report["rmse_geometric_mm"],
        "effects": [e["name"] for e in report["effects"]],
        "total_wall_s": res["wall_s"],
        "peak_mb": res["peak_mb"],
    }


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
