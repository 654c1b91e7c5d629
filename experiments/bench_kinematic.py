"""``torchcal calibrate --method kinematic`` against a plain numpy Gauss-Newton reference
(:mod:`experiments.numpy_reference`) on the same rows (``scripts/bench_kinematic.py``).

:func:`write_problem` writes, once and untimed, what the reference takes from torchcal: the robot's nominal DH
table and the training and held-out rows of calibrate's split (``torchcal.pipeline.run.holdout_split``: seeded,
revisits grouped), so that the reference's process imports numpy only. :func:`compare` then times both as commands,
each in a fresh process with one thread (``OMP_NUM_THREADS=1``, as ``scripts/bench_memory.py``), alternating, and
takes each one's shortest wall and CPU time; then each one's fit alone in this process (torchcal's
``pipeline.calibrate``, the reference's ``calibrate``), alternating too. The ratio is torchcal over the reference.

Before the commands, torchcal's modules are compiled to bytecode (``compileall``, into the checkout's ignored
``__pycache__``), as an installed package has them: where the environment sets ``PYTHONDONTWRITEBYTECODE`` and
nothing compiled them, every command compiles torchcal's sources again (``bytecode="as found"`` measures it that
way).
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from experiments import numpy_reference as ref
from torchcal.errors import TorchcalError

REFERENCE = Path(ref.__file__).resolve()
#: how torchcal's modules are found before the commands run (:func:`compare`)
BYTECODE = ("compiled", "as found")


def write_problem(data: str, robot: str, path: Path) -> dict:
    """Write the reference's problem file (module docstring) for ``data`` and the built-in or DH ``robot``;
    return it."""
    from torchcal import stats as S
    from torchcal.data import read_measurements
    from torchcal.pipeline import Options
    from torchcal.pipeline.run import holdout_split, is_trajectory
    from torchcal.robot import load_robot
    from torchcal.robot.model import DHConvention

    model = load_robot(robot)
    g = model.geometry
    if getattr(g, "convention", None) is not DHConvention.STANDARD or model.has_readings_map:
        raise TorchcalError(f"the numpy reference takes a standard-DH robot read as its joints, not '{robot}'")
    m = read_measurements(data, dof=model.dof)
    opts = Options.of(method="kinematic")
    split = holdout_split(m, opts.split.holdout, opts.seed + S.Stream.HOLDOUT, is_trajectory(m), opts.split.group_tol)
    problem = {
        "robot": robot,
        "dh": g.nominal[:, :4].tolist(),
        "train": split.keep.tolist(),
        "holdout": split.held.tolist(),
    }
    path.write_text(json.dumps(problem))
    return problem


def _timed(argv: list[str]) -> dict:
    """Run ``argv`` in a fresh process with one thread: its wall time and its CPU time (user + system, from the
    children's resource usage), and its stdout."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise TorchcalError(f"{' '.join(argv)} failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu, "stdout": proc.stdout}


def torchcal_command(data: str, robot: str, out: Path) -> list[str]:
    """``torchcal calibrate DATA --robot R --method kinematic --out OUT --quiet`` (``python -m torchcal``)."""
    return [sys.executable, "-m", "torchcal", "calibrate", data, "--robot", robot, "--method", "kinematic"] + [
        "--out",
        str(out),
        "--quiet",
    ]


def commands(data: str, robot: str, problem: Path, work: Path, repeats: int) -> dict:
    """Both commands ``repeats`` times, alternating; every run's times and each one's shortest."""
    runs: dict[str, list[dict]] = {"torchcal": [], "reference": []}
    out = work / "run"
    for _ in range(repeats):
        shutil.rmtree(out, ignore_errors=True)
        runs["torchcal"].append(_timed(torchcal_command(data, robot, out)))
        runs["reference"].append(_timed([sys.executable, str(REFERENCE), data, "--problem", str(problem)]))
    report = json.loads((out / "report.json").read_text())
    result = json.loads(runs["reference"][-1]["stdout"].strip().splitlines()[-1])
    best = {k: {t: min(r[t] for r in v) for t in ("wall_s", "cpu_s")} for k, v in runs.items()}
    return {
        "runs": {k: [{t: r[t] for t in ("wall_s", "cpu_s")} for r in v] for k, v in runs.items()},
        "best": best,
        "rmse_holdout_mm": {"torchcal": report["rmse_geometric_mm"], "reference": result["rmse_holdout_mm"]},
        "reference": {k: v for k, v in result.items() if k != "parameters"},
    }


@contextlib.contextmanager
def orientation_jacobian_clock():
    """Count the CPU seconds and calls of the orientation rows' Jacobians (``torch.func.jacfwd`` through the chain,
    :func:`torchcal.estimate.problem.orientation_function`) of the fits inside the block: yields the running
    ``{"cpu_s", "calls"}``."""
    from torchcal.estimate import fit as F

    spent = {"cpu_s": 0.0, "calls": 0}
    plain = F.orientation_function

    def clocked(*args, **kw):
        fun = plain(*args, **kw)
        jacobian = fun.jacobian

        def timed(x):
            c0 = time.process_time()
            try:
                return jacobian(x)
            finally:
                spent["cpu_s"] += time.process_time() - c0
                spent["calls"] += 1

        fun.jacobian = timed
        return fun

    F.orientation_function = clocked
    try:
        yield spent
    finally:
        F.orientation_function = plain


def fits(data: str, robot: str, problem: dict, repeats: int) -> dict:
    """Each fit alone in this process (data read and robot loaded before the clock), alternating, shortest of
    ``repeats``: torchcal's ``pipeline.calibrate`` with the kinematic method, the reference's ``calibrate``; and, of
    torchcal's shortest, the CPU seconds its orientation rows' Jacobians took (:func:`orientation_jacobian_clock`)."""
    import torch

    from torchcal.data import read_measurements
    from torchcal.pipeline import Options, calibrate
    from torchcal.robot import load_robot

    robot_model = load_robot(robot)
    m = read_measurements(data, dof=robot_model.dof)
    cols = ref.read_csv(data)
    dh4 = np.asarray(problem["dh"])
    q = np.stack([cols[f"q{i + 1}"] for i in range(len(dh4))], axis=1)
    p = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
    train, hold = np.asarray(problem["train"]), np.asarray(problem["holdout"])
    times: dict[str, list[tuple[float, float, dict]]] = {"torchcal": [], "reference": []}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for _ in range(repeats):
            for name, fit in (
                ("torchcal", lambda: calibrate(robot_model, m, Options.of(method="kinematic"), robot_spec=robot)),
                ("reference", lambda: ref.calibrate(dh4, q, p, train, hold)),
            ):
                with orientation_jacobian_clock() as spent:
                    t0, c0 = time.perf_counter(), time.process_time()
                    fit()
                    times[name].append((time.perf_counter() - t0, time.process_time() - c0, dict(spent)))
    finally:
        torch.set_num_threads(threads)
    out = {k: {"wall_s": min(t[0] for t in v), "cpu_s": min(t[1] for t in v)} for k, v in times.items()}
    best = min(times["torchcal"], key=lambda t: t[1])
    out["torchcal"]["orientation_jacobian"] = best[2]
    return out


def compile_torchcal() -> None:
    """Compile the imported torchcal package's modules to bytecode (``python -m compileall -q``)."""
    import torchcal

    package = Path(torchcal.__file__).resolve().parent
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(package)], check=True, capture_output=True)


def compare(data: str, robot: str, work: Path, repeats: int = 3, bytecode: str = "compiled") -> dict:
    """The benchmark (module docstring): problem file, commands, fits, and the ratios torchcal / reference.
    ``bytecode``: ``"compiled"`` (torchcal compiled first) or ``"as found"``."""
    if bytecode not in BYTECODE:
        raise TorchcalError(f"bytecode must be one of {', '.join(BYTECODE)}, got {bytecode!r}")
    if bytecode == "compiled":
        compile_torchcal()
    problem_path = work / "problem.json"
    problem = write_problem(data, robot, problem_path)
    cmd = commands(data, robot, problem_path, work, repeats)
    fit = fits(data, robot, problem, repeats)
    ratio = {
        "command_wall": cmd["best"]["torchcal"]["wall_s"] / cmd["best"]["reference"]["wall_s"],
        "command_cpu": cmd["best"]["torchcal"]["cpu_s"] / cmd["best"]["reference"]["cpu_s"],
        "fit_wall": fit["torchcal"]["wall_s"] / fit["reference"]["wall_s"],
        "fit_cpu": fit["torchcal"]["cpu_s"] / fit["reference"]["cpu_s"],
    }
    return {
        "data": data,
        "robot": robot,
        "repeats": repeats,
        "bytecode": bytecode,
        "n_train": len(problem["train"]),
        "n_holdout": len(problem["holdout"]),
        "command": cmd,
        "fit": fit,
        "ratio": ratio,
        "load_average": os.getloadavg()[0],
    }
