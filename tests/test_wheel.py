"""The wheel works outside the repository: it carries the built-in robots and the licence.

Builds the wheel from a copy of the source tree (offline: no build isolation, no downloads), installs it
into a fresh virtual environment that sees the test environment's packages (torch, yourdfpy, ...) but
not the source tree, and runs the installed ``torchcal`` command from an unrelated directory.

The demo takes a minute or more on a busy machine, so the end-to-end run here is ``simulate`` +
``calibrate --method kinematic`` + ``predict`` with the built-in robots, which exercises the same
installed code paths (package data, entry point, run directory) in a few seconds.
"""

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(cmd, cwd, env, timeout=300):
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{cmd} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}"
    return r


@pytest.mark.slow
def test_wheel_installs_and_runs_outside_the_source_tree(tmp_path):
    # a copy of the tracked sources, so the build leaves nothing (build/, *.egg-info) in the checkout
    pytest.importorskip(
        "setuptools",
        minversion="77",
        reason="building the wheel offline needs setuptools>=77 in the test environment (the dev extra installs it)",
    )
    src = tmp_path / "src"
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True, text=True)
    if listed.returncode == 0:
        for f in listed.stdout.splitlines():
            if (ROOT / f).is_file():
                (src / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / f, src / f)
    else:  # not a git checkout (an unpacked sdist): everything but environments and outputs
        shutil.copytree(
            ROOT,
            src,
            ignore=shutil.ignore_patterns(
                ".venv", "runs", "build", "*.egg-info", ".git", "__pycache__", ".pytest_cache", ".ruff_cache"
            ),
        )
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "TORCHCAL_ROBOTS")}
    env["OMP_NUM_THREADS"] = "1"
    dist = tmp_path / "dist"
    r = _run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            str(src),
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "-w",
            str(dist),
        ],
        cwd=tmp_path,
        env=env,
    )
    assert "project.license" not in r.stderr  # the licence is an SPDX string, not the deprecated table
    wheel = next(dist.glob("torchcal-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for robot in ("ur5.yaml", "ur5.urdf", "ur10.yaml", "ur10.urdf", "panda.urdf", "panda.yaml"):
        assert f"torchcal/robots/{robot}" in names
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    # the scripts' experiment code runs from a checkout; a user's wheel has the library only
    assert not [n for n in names if n.startswith("experiments/")] and "torchcal/pipeline/run.py" in names

    # a fresh venv that sees the test environment's site-packages through a .pth line (its .pth files,
    # among them the editable install's finder of the source tree, are not run: only the path is added)
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=tmp_path, env=env)
    py = venv / "bin" / "python"
    vsite = Path(
        subprocess.run(
            [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True,
            text=True,
            check=True,
            env=env,
        ).stdout.strip()
    )
    (vsite / "outer.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run(
        [sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", str(wheel)],
        cwd=tmp_path,
        env=env,
    )

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = _run([str(py), "-c", "import torchcal; print(torchcal.__file__)"], cwd=elsewhere, env=env).stdout
    assert Path(where.strip()).is_relative_to(venv), where
    exe = str(venv / "bin" / "torchcal")
    listed = _run(
        [str(py), "-c", "from torchcal.robot import builtin_robots; print(builtin_robots())"], cwd=elsewhere, env=env
    ).stdout
    assert "ur5" in listed and "panda.urdf" in listed
    _run(
        [exe, "simulate", "--robot", "ur5", "--out", "sim", "--poses", "120", "--test-poses", "30", "--quiet"],
        cwd=elsewhere,
        env=env,
    )
    _run(
        [exe, "calibrate", "sim/train.csv", "--robot", "ur5", "--method", "kinematic", "--out", "cal", "--quiet"],
        cwd=elsewhere,
        env=env,
    )
    _run([exe, "predict", "cal", "sim/test.csv", "--out", "pred.csv", "--quiet"], cwd=elsewhere, env=env)
    assert (elsewhere / "cal" / "report.json").is_file() and (elsewhere / "pred.csv").is_file()
    _run([str(py), "-c", "import torchcal; assert torchcal.load_robot('panda.urdf').dof == 7"], cwd=elsewhere, env=env)
