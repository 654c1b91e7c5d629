"""Where the default method's time goes (``scripts/profile_calibration.py``, issue 37).

Two runs of ``torchcal calibrate DATA --robot R`` (the default method), each in a fresh process with one torch thread:

* through the memory probe (:func:`experiments.bench_calibration.stages`): wall and CPU seconds of each stage of the
  pipeline (screening, nominal and kinematic fits, closed loop, learned stage, guard, finish, report with its trust
  columns, URDF, report.md and its figures) and of the stages nested in them (:data:`STAGES` on top of
  :data:`~experiments.bench_calibration.PARTS`); a part's CPU time is the whole process's while it ran;
* under ``cProfile`` (:mod:`experiments._cprofile_run`, every thread its own profiler, each thread's CPU time as the
  timer; from Python 3.12 one profiler for all threads on the process's CPU time): the kernels of :data:`KERNELS`
  (calls, CPU seconds including what they call, share of the process's CPU) and the torchcal functions that spend
  the most CPU themselves, the time of what they call outside torchcal (torch, matplotlib) charged to them
  (:func:`own_times`). The profiler's own cost inflates the CPU time of functions with many small calls; the shares
  are what to read.

:func:`simulated` makes the second data set: a simulated campaign of a 7-axis arm with orientations (a 6-D probe).
:func:`compare` times the default method against a baseline source tree, alternating, as commands;
:func:`compare_commits` times pairs of commits of this checkout (a change against the code before it) the same way.
"""

from __future__ import annotations

import importlib
import inspect
import json
import os
import pstats
import resource
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

from experiments.bench_calibration import PARTS, stages
from torchcal.errors import TorchcalError

PROFILER = Path(__file__).resolve().with_name("_cprofile_run.py")

#: the top-level stages of the pipeline and the report, as ``MODULE:ATTR=NAME`` for the memory probe, besides its own
#: (:data:`experiments._memprobe.TARGETS`) and :data:`~experiments.bench_calibration.PARTS`; a method's stages are
#: held in its table, so the functions they call are wrapped (looked up where they are called)
STAGES = [
    "torchcal.pipeline.methods:guard_stages=guard",
    "torchcal.pipeline.methods:_covariance=finish: covariance",
    "torchcal.pipeline.trust:run_trust=trust columns",
    "torchcal.report.markdown:subplots=plots",
    "torchcal.report.markdown:save=plots",
]

#: the kernels the profile names: label -> functions (``module:qualified name``, nested functions by their path); a
#: function's CPU time includes what it calls
KERNELS = {
    "least-squares fits (LM)": ["torchcal.estimate.lm:levenberg_marquardt"],
    # _ladder: an iteration's trial points in one batched call; _attempt: one point (damping harder, or the fallback)
    "LM: damping ladder (residuals)": ["torchcal.estimate.lm:_ladder", "torchcal.estimate.lm:_attempt"],
    "LM: position Jacobians": ["torchcal.estimate.problem:residual_function.jacobian"],
    "LM: orientation Jacobians": ["torchcal.estimate.problem:orientation_function.jacobian"],
    "identifiability analyses": ["torchcal.estimate.identifiability:analyse"],
    "screening (robust fit)": ["torchcal.estimate.robust:screen_geometric"],
    "loop: score tests": ["torchcal.diagnose.score:score_candidates"],
    "loop: localisation": ["torchcal.diagnose.tracing:localise_fit"],
    "loop: validation refits": ["torchcal.pipeline.loop:_validate", "torchcal.pipeline.loop:_validate_edge"],
    "loop: accepted refits": ["torchcal.pipeline.loop:_accept"],
    "learned: GP fits": ["torchcal.effects.gp:fit_gp_correction"],
    "learned: GP evidence (L-BFGS)": ["torchcal.effects.gp:fit_hyperparameters"],
    "learned: kernel regression fits": ["torchcal.effects.kernel:fit_kernel_correction"],
    "learned: network fits": ["torchcal.estimate.netfit:fit_net"],
    "learned: geometry refits": ["torchcal.pipeline.learned:_refit_geometry"],
    "guard": ["torchcal.pipeline.holdout:guard_stages"],
    "report.json": ["torchcal.report.rundir:build_report"],
    "trust columns": ["torchcal.pipeline.trust:run_trust"],
    "figures": ["torchcal.report._figures:subplots", "torchcal.report._figures:save"],
    "kinematic chain (all callers)": ["torchcal.robot.model:RobotModel._chain_t"],
    "gravity torques (all callers)": ["torchcal.robot.model:RobotModel.gravity_torques"],
}


def simulated(robot: str, poses: int, seed: int, work: Path) -> Path:
    """A simulated campaign of ``robot`` with orientations (``--orientation 0.01``: a 6-D probe) and a compliance at
    joint 2 (the closed loop then has an effect to find); returns its training file."""
    out = work / f"sim-{Path(robot).stem}"
    argv = ["simulate", "--robot", robot, "--poses", str(poses), "--seed", str(seed), "--orientation", "0.01"]
    argv += ["--effect", "compliance:2=50um", "--out", str(out), "--quiet"]
    _torchcal(argv)
    return out / "train.csv"


def _torchcal(argv: list[str]) -> None:
    proc = subprocess.run([sys.executable, "-m", "torchcal", *argv], capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise TorchcalError(f"torchcal {' '.join(argv)} failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")


def cprofile(data: str, robot: str, method: str, work: Path) -> pstats.Stats:
    """``torchcal calibrate DATA --robot ROBOT --method METHOD`` under ``cProfile`` in a fresh process (one torch
    thread), every thread profiled by its CPU time; the merged statistics."""
    out = work / "calibrate.prof"
    argv = ["calibrate", str(data), "--robot", robot, "--method", method, "--out", str(work / "run"), "--quiet"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, str(PROFILER), str(out), "--", *argv], capture_output=True, text=True, env=env, check=False
    )
    if proc.returncode != 0:
        raise TorchcalError(f"torchcal {' '.join(argv)} failed under cProfile: {proc.stderr.strip()[-2000:]}")
    return pstats.Stats(str(out))


def _code_key(target: str) -> tuple[str, int, str]:
    """``module:qualified.name`` -> the profiler's key of that function (file, first line, name); a nested function
    is named by its path (``outer.inner``), found among the code objects of the outer one."""
    mod, _, qual = target.partition(":")
    parts = qual.split(".")
    obj = importlib.import_module(mod)
    code = None
    for p in parts:
        if code is None and hasattr(obj, p):
            obj = getattr(obj, p)
            if inspect.isfunction(obj) or inspect.ismethod(obj):
                code = inspect.unwrap(obj).__code__
            continue
        if code is None:
            raise KeyError(f"{target}: no {p} in {obj}")
        inner = [c for c in code.co_consts if inspect.iscode(c) and c.co_name == p]
        if not inner:
            raise KeyError(f"{target}: no nested function {p} in {code.co_name}")
        code = inner[0]
    return code.co_filename, code.co_firstlineno, code.co_name


def kernel_table(stats: pstats.Stats, total: float) -> list[dict]:
    """Each kernel of :data:`KERNELS`: calls and CPU seconds with what it calls (summed over its functions; a
    function called inside another of the same label is counted twice only where both are named), share of
    ``total``."""
    rows = []
    for label, targets in KERNELS.items():
        calls, cum = 0, 0.0
        for t in targets:
            entry = stats.stats.get(_code_key(t))
            if entry is None:
                continue
            _, nc, _, ct, _ = entry
            calls += nc
            cum += ct
        rows.append({"kernel": label, "calls": calls, "cpu_s": cum, "share": cum / total if total else 0.0})
    return rows


def _is_own(key: tuple[str, int, str], root: str) -> bool:
    return key[0].startswith(root)


def own_times(stats: pstats.Stats, root: str, top: int = 20, rounds: int = 500) -> list[dict]:
    """The torchcal functions (file under ``root``) that spend the most CPU: their own time plus that of the functions
    outside torchcal they call, down to the next torchcal function. The own time of a function outside torchcal goes
    to its callers in proportion to the time each call edge took (as gprof shares it), passed on from caller to
    caller (a recursive call's own edge left out) until a torchcal function takes it, for at most ``rounds`` steps;
    time with no torchcal caller (the imports) is ``(outside torchcal)``."""
    table = stats.stats
    own: dict = defaultdict(float)
    calls: dict = {}
    mass: dict = {}
    for key, (_, nc, tt, _, _) in table.items():
        if _is_own(key, root):
            own[key] += tt
            calls[key] = nc
        elif tt > 0:
            mass[key] = tt
    for _ in range(rounds):
        moved: dict = defaultdict(float)
        for key, m in mass.items():
            callers = {c: e[3] for c, e in table[key][4].items() if e[3] > 0 and c != key} if key in table else {}
            total = sum(callers.values())
            if not total:
                own[None] += m
                continue
            for c, w in callers.items():
                if _is_own(c, root):
                    own[c] += m * w / total
                else:
                    moved[c] += m * w / total
        mass = moved
        if sum(mass.values()) < 1e-6:
            break
    own[None] += sum(mass.values())
    total = sum(own.values())
    rows = sorted(own.items(), key=lambda kv: -kv[1])[:top]
    return [
        {
            "function": "(outside torchcal)" if k is None else f"{Path(k[0]).relative_to(Path(root).parent)}:{k[2]}",
            "line": None if k is None else k[1],
            "calls": None if k is None else calls.get(k),
            "cpu_s": v,
            "share": v / total if total else 0.0,
        }
        for k, v in rows
    ]


def profile(data: str, robot: str, method: str, work: Path) -> dict:
    """One data set: the stages (memory probe) and the kernels (cProfile) of one calibration each."""
    import torchcal

    work.mkdir(parents=True, exist_ok=True)
    st = stages(data, robot, method, work / "stages", parts=PARTS + STAGES)
    stats = cprofile(data, robot, method, work / "cprofile")
    root = str(Path(torchcal.__file__).resolve().parent) + "/"
    total = sum(e[2] for e in stats.stats.values())
    return {
        "data": str(data),
        "robot": robot,
        "method": method,
        **st,
        "profiled_cpu_s": total,
        "kernels": kernel_table(stats, total),
        "own": own_times(stats, root),
    }


def calibrate_once(tree: Path, data: str, robot: str, method: str, out: Path) -> dict:
    """One ``torchcal calibrate`` as a command with ``tree``'s torchcal (one torch thread): its wall and CPU seconds
    (the CPU time counts beside other work, where the wall time counts the others too) and its report's held-out
    RMSE and effects."""
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    argv = ["calibrate", str(data), "--robot", robot, "--method", method, "--out", str(out), "--quiet"]
    t0, c0 = time.perf_counter(), _child_cpu()
    # run in the tree: ``python -m`` puts the working directory first on the path
    done = subprocess.run([sys.executable, "-m", "torchcal", *argv], env=env, cwd=tree, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, _child_cpu() - c0
    if done.returncode != 0:
        raise TorchcalError(f"{tree}: torchcal {' '.join(argv)} exited {done.returncode}: {done.stderr[-1000:]}")
    report = json.loads((out / "report.json").read_text())
    return {
        "wall_s": wall,
        "cpu_s": cpu,
        "rmse_holdout_mm": report["rmse_after_mm"],
        "effects": [e["name"] for e in report["effects"]],
    }


def _child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def compare(data: str, robot: str, baseline: Path, repeat: int, work: Path) -> dict:
    """This tree's default method against ``baseline``'s (a torchcal source tree, e.g. the commit before a speed-up)
    on ``data``, ``repeat`` times alternating, then this tree's kinematic method once per round too: every run's
    seconds, the medians, this tree's CPU and wall time over the baseline's and over its own kinematic calibration's,
    and how far the two trees' held-out RMSEs are apart and whether their effects agree."""
    ours_tree = Path(__file__).resolve().parents[1]
    runs: dict[str, list[dict]] = {"ours": [], "baseline": [], "kinematic": []}
    for k in range(repeat):
        for name, tree, method in (("ours", ours_tree, "auto"), ("baseline", baseline, "auto")) + (
            ("kinematic", ours_tree, "kinematic"),
        ):
            runs[name].append(calibrate_once(tree, data, robot, method, work / f"{name}{k}"))
            print(f"round {k + 1}: {name}: {json.dumps(runs[name][-1])}", file=sys.stderr, flush=True)

    def med(name: str, key: str) -> float:
        return statistics.median(r[key] for r in runs[name])

    return {
        "data": str(data),
        "robot": robot,
        "baseline": str(baseline),
        "runs": runs,
        "cpu_ratio_to_baseline": med("ours", "cpu_s") / med("baseline", "cpu_s"),
        "wall_ratio_to_baseline": med("ours", "wall_s") / med("baseline", "wall_s"),
        "cpu_ratio_to_kinematic": med("ours", "cpu_s") / med("kinematic", "cpu_s"),
        "baseline_cpu_ratio_to_kinematic": med("baseline", "cpu_s") / med("kinematic", "cpu_s"),
        "wall_ratio_to_kinematic": med("ours", "wall_s") / med("kinematic", "wall_s"),
        "same_effects": all(a["effects"] == b["effects"] for a, b in zip(runs["ours"], runs["baseline"])),
        "rmse_holdout_max_diff_mm": max(
            abs(a["rmse_holdout_mm"] - b["rmse_holdout_mm"]) for a, b in zip(runs["ours"], runs["baseline"])
        ),
        "rmse_holdout_mm": {n: runs[n][0]["rmse_holdout_mm"] for n in runs},
    }


def commit_tree(commit: str, work: Path) -> Path:
    """The torchcal package and robot files of ``commit`` of this checkout, unpacked under ``work`` once."""
    root = Path(__file__).resolve().parents[1]
    tree = work / f"tree-{commit}"
    if not tree.is_dir():
        tree.mkdir(parents=True)
        archive = subprocess.run(
            ["git", "-C", str(root), "archive", commit, "torchcal", "robots"], capture_output=True, check=False
        )
        if archive.returncode != 0:
            raise TorchcalError(f"git archive {commit}: {archive.stderr.decode(errors='replace').strip()}")
        subprocess.run(["tar", "-x", "-C", str(tree)], input=archive.stdout, check=True)
    return tree


def compare_commits(data: str, robot: str, pairs: list[tuple[str, str]], repeat: int, work: Path) -> dict:
    """Each pair ``(before, after)`` of commits: the default method of both on ``data`` as commands, ``repeat``
    rounds, the order flipped every round (a machine that slows during a round charges both); per pair the CPU
    seconds, the ratio of the medians and of the minima, the ratio of each round, and whether the held-out RMSE and
    effects agree; and the product of the pairs' ratios of the medians (a series of changes, each against the code
    before it)."""
    out, product = [], 1.0
    for before, after in pairs:
        runs: dict[str, list[dict]] = {before: [], after: []}
        for k in range(repeat):
            for c in (before, after) if k % 2 == 0 else (after, before):
                runs[c].append(calibrate_once(commit_tree(c, work), data, robot, "auto", work / f"run-{c}-{k}"))
                print(f"round {k + 1}: {c}: {json.dumps(runs[c][-1])}", file=sys.stderr, flush=True)
        cpu = {c: [r["cpu_s"] for r in runs[c]] for c in runs}
        ratio = statistics.median(cpu[after]) / statistics.median(cpu[before])
        product *= ratio
        out.append(
            {
                "before": before,
                "after": after,
                "cpu_s": cpu,
                "cpu_ratio": ratio,
                # noise on a shared machine only adds time: the fastest run is the code's own cost
                "cpu_ratio_of_minima": min(cpu[after]) / min(cpu[before]),
                "round_ratios": [a / b for a, b in zip(cpu[after], cpu[before])],
                "same_results": all(
                    (a["rmse_holdout_mm"], a["effects"]) == (b["rmse_holdout_mm"], b["effects"])
                    for a, b in zip(runs[before], runs[after])
                ),
            }
        )
    return {"data": str(data), "robot": robot, "repeat": repeat, "pairs": out, "cpu_ratio_product": product}
