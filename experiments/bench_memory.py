"""Peak memory and time of each stage of a ``torchcal`` command (``scripts/bench_memory.py``).

:func:`measure` runs one command line of the CLI (``calibrate DATA --robot R --method kinematic --out DIR``, or
``simulate ...``) in a fresh interpreter with one torch thread through :mod:`experiments._memprobe`, which
wraps the command's stages as their modules are imported and reports, per stage, the calls, wall and CPU
seconds, the stage's own peak resident memory (the kernel's high-water mark, reset at every stage boundary: torch's
allocator is invisible to ``tracemalloc``), the resident memory before and after it, and the packages it imported.
Stages nest (``command/fit/screening``); the peak of a stage includes its children's.

:func:`calibration` measures ``calibrate`` of a measurement file; :func:`campaign` first simulates an ``n``-row
campaign (measured too) and then measures ``calibrate`` of its training file.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from torchcal.errors import TorchcalError

PROBE = Path(__file__).resolve().with_name("_memprobe.py")


def measure(argv: list[str], *, targets: list[str] = (), reset: bool = True) -> dict:
    """Run ``torchcal ARGV`` in a fresh process (one torch thread) and return its stages.

    Args:
        argv: the CLI's arguments after ``torchcal``.
        targets: further stages, ``MODULE:ATTR=NAME`` (the attribute is wrapped where it is looked up).
        reset: reset the high-water mark at every stage boundary (False: each stage's peak is the process's so
            far, as ``ru_maxrss`` gives it).

    Returns:
        ``{"argv", "rc", "peak_mb", "peak_reset", "start_rss_mb", "stages": [...], "wall_s"}``: ``peak_mb`` the
        largest resident set of the process [MB], ``wall_s`` the whole process's wall time with the interpreter's
        start.
    """
    opts = [] if reset else ["--no-reset"]
    for t in targets:
        opts += ["--target", t]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, str(PROBE), *opts, "--", *argv], capture_output=True, text=True, env=env, check=False
    )
    wall = time.perf_counter() - t0
    lines = proc.stdout.strip().splitlines()
    if proc.returncode != 0 or not lines:
        raise TorchcalError(
            f"torchcal {' '.join(argv)} failed (exit {proc.returncode}) under the memory probe: "
            f"{proc.stderr.strip()[-2000:]}"
        )
    out = json.loads(lines[-1])
    out["wall_s"] = wall
    return out


def calibration(data: str, robot: str, method: str, out: Path, *, targets: list[str] = ()) -> dict:
    """``torchcal calibrate DATA --robot ROBOT --method METHOD --out OUT --quiet``, measured (:func:`measure`)."""
    argv = ["calibrate", str(data), "--robot", robot, "--method", method, "--out", str(out), "--quiet"]
    return measure(argv, targets=targets)


def campaign(n: int, robot: str, method: str, work: Path, *, seed: int = 1, targets: list[str] = ()) -> dict:
    """Simulate an ``n``-row campaign (``torchcal simulate --poses n``), then calibrate its training file; both
    measured. Returns ``{"simulate": ..., "calibrate": ...}``."""
    sim_dir = work / f"sim{n}"
    sim = measure(
        ["simulate", "--robot", robot, "--poses", str(n), "--test-poses", "100", "--seed", str(seed), "--out"]
        + [str(sim_dir), "--quiet"],
        targets=targets,
    )
    cal = calibration(str(sim_dir / "train.csv"), robot, method, work / f"run{n}", targets=targets)
    return {"simulate": sim, "calibrate": cal}


def table(result: dict) -> str:
    """The stages of one :func:`measure` result as a text table (one line per stage)."""
    rows = [f"{'stage':58s} {'calls':>5s} {'wall s':>7s} {'cpu s':>7s} {'peak MB':>8s} {'RSS MB before->after':>21s}"]
    for s in result["stages"]:
        rows.append(
            f"{s['stage'][:58]:58s} {s['calls']:5d} {s['wall_s']:7.2f} {s['cpu_s']:7.2f} {s['peak_mb']:8.1f} "
            f"{s['rss_before_mb']:9.1f} -> {s['rss_after_mb']:7.1f}"
        )
    rows.append(
        f"peak {result['peak_mb']:.1f} MB, process wall {result['wall_s']:.2f} s: torchcal {' '.join(result['argv'])}"
    )
    return "\n".join(rows)
