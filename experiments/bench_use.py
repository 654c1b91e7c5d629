"""CPU and wall time of the commands that use a run (``predict``, ``compensate``, ``plan``), this tree against a
baseline source tree, each as a command (the import included, as a user waits for it), alternating, and whether
their outputs agree (``scripts/bench_use.py``).

Each case runs under two thread settings: ``default`` (no ``OMP_NUM_THREADS``: what a user gets) and ``1``
(``OMP_NUM_THREADS=1``: the commands' own work, without torch's thread team). Python's bytecode goes to a cache of
the benchmark's own, filled before the first timed run, so that no run compiles sources (an installed package
ships its bytecode).
"""

from __future__ import annotations

import csv
import math
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from experiments import common

#: outputs agree where every number does to this relative difference, or to ABS_FLOOR [m, rad]: compensate's miss
#: and miss_angle are what the solver leaves below its tolerance (1e-10), and a miss of 2e-12 rad from one tree
#: against 2.002e-12 from the other is no disagreement
RELATIVE = 1e-12
ABS_FLOOR = 1e-12


@dataclass
class Case:
    """One command: its name, its arguments after ``torchcal`` (``{out}`` stands for the output file)."""

    name: str
    argv: list[str]


def cases(run: str | None, data: str | None, targets: str | None, plan_n: list[int], robot: str) -> list[Case]:
    """The cases the arguments ask for: predict of ``data`` and compensate of ``targets`` with the run ``run``, and
    ``plan --n N`` of ``robot`` for each ``plan_n``."""
    out = []
    if run and data:
        out.append(Case("predict", ["predict", run, data, "--out", "{out}"]))
    if run and targets:
        out.append(Case("compensate", ["compensate", run, targets, "--out", "{out}"]))
    out += [Case(f"plan --n {n}", ["plan", "--robot", robot, "--n", str(n), "--out", "{out}"]) for n in plan_n]
    return out


def environment(tree: Path, threads: str, cache: Path) -> dict:
    """The environment of a command of ``tree``'s torchcal under the thread setting ``threads``."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.update(PYTHONPATH=str(tree), PYTHONPYCACHEPREFIX=str(cache))
    if threads != "default":
        env.update(OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
    return env


def compile_tree(tree: Path, cache: Path) -> None:
    """Fill the bytecode cache with ``tree``'s torchcal and what its commands import (torch's modules among them:
    the cache takes every module's bytecode, and the first timed run would otherwise compile torch), outside the
    timings."""
    env = environment(tree, "1", cache)
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(tree / "torchcal")], env=env, check=True)
    imports = "import torchcal.cli, torchcal.use.rundir, torchcal.use.compensate, torchcal.use.plan, torchcal.data"
    subprocess.run([sys.executable, "-c", imports], env=env, cwd=tree, check=True)


def run_once(tree: Path, case: Case, out: Path, threads: str, cache: Path) -> tuple[float, float]:
    """Wall and CPU seconds of one command of ``tree``'s torchcal (the CPU time of the child alone, where the wall
    time counts the other work of a shared machine too); raises where it fails."""
    argv = [a.replace("{out}", str(out)) for a in case.argv] + ["--quiet", "--force"]
    # run in the tree: ``python -m`` puts the working directory first on the path
    return common.timed_command(
        [sys.executable, "-m", "torchcal", *argv],
        env=environment(tree, threads, cache),
        cwd=tree,
        what=f"{tree}: {case.name}",
    )


def agreement(a: Path, b: Path) -> dict:
    """How far two CSV outputs differ: the largest relative difference of a number and its column, and whether
    they agree (:data:`RELATIVE`, :data:`ABS_FLOOR`); text cells must be equal."""
    ra, rb = _rows(a), _rows(b)
    if ra[0] != rb[0] or len(ra) != len(rb):
        return {"agree": False, "why": "different columns or rows"}
    worst, column, agree = 0.0, None, True
    for row_a, row_b in zip(ra[1:], rb[1:]):
        for name, x, y in zip(ra[0], row_a, row_b):
            if x == y:
                continue
            try:
                fx, fy = float(x), float(y)
            except ValueError:
                return {"agree": False, "why": f"column {name}: {x!r} against {y!r}"}
            diff, size = abs(fx - fy), max(abs(fx), abs(fy))
            agree = agree and diff <= RELATIVE * size + ABS_FLOOR
            rel = diff / size if size > 0 else math.inf
            if diff > ABS_FLOOR and rel > worst:
                worst, column = rel, name
    return {"agree": agree, "max_relative": float(f"{worst:.3g}"), "column": column}


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as f:
        return list(csv.reader(line for line in f if not line.startswith("#")))


def compare(base: Path, here: Path, case: Case, threads: str, repeat: int, tmp: Path, cache: Path) -> dict:
    """One case under one thread setting: both trees ``repeat`` times, alternating (the first tree of each repeat
    alternates too), the smallest CPU time of each and its wall time, their ratios and the outputs' agreement."""
    runs: dict[str, list[tuple[float, float]]] = {"here": [], "base": []}
    trees = {"here": here, "base": base}
    for i in range(repeat):
        for who in ("here", "base") if i % 2 == 0 else ("base", "here"):
            runs[who].append(run_once(trees[who], case, tmp / f"{who}.csv", threads, cache))
    here_t, base_t = (min(runs[w], key=lambda r: r[1]) for w in ("here", "base"))
    return {
        "case": case.name,
        "threads": threads,
        "cpu_seconds": round(here_t[1], 2),
        "seconds": round(here_t[0], 2),
        "baseline_cpu_seconds": round(base_t[1], 2),
        "baseline_seconds": round(base_t[0], 2),
        "cpu_speedup": round(base_t[1] / here_t[1], 2),
        "wall_speedup": round(base_t[0] / here_t[0], 2),
        "outputs": agreement(tmp / "base.csv", tmp / "here.csv"),
    }
