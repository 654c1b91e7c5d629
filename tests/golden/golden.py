"""Regenerate the golden reports: ``python tests/golden/golden.py`` (writes ``*.json`` next to this file).

A small, fast, seeded run per method on a simulated UR5 campaign (200 poses, joint-2 compliance and a
smooth field the nominal model lacks), reduced to the run's ``report.json`` (:func:`build_report`).
``tests/test_golden.py`` compares a fresh run against the stored report key by key (discrete results exactly,
numbers to the tolerances its docstring justifies, which the BLAS kernels of another CPU stay well inside), so a
refactoring that changes a number, a stage, an effect or a note shows up. Regenerate only when a change of the
results is intended, and say why in the commit.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: method -> calibration options (beside the method) of each golden run
CASES = {
    "kinematic": {},
    "auto": {},
    "kinematic+ann": {"net_iterations": 30},
}
SIM = {"robot": "ur5", "poses": 200, "test_poses": 20, "seed": 7, "effects": ("compliance:2=60um", "field=0.05mm")}


def campaign():
    """The golden runs' simulated campaign (:data:`SIM`); other tests reuse it (``tests/_cli.golden_campaign``)."""
    from torchcal.sim import EffectSpec, SimConfig, simulate

    cfg = SimConfig(
        robot=SIM["robot"],
        poses=SIM["poses"],
        test_poses=SIM["test_poses"],
        seed=SIM["seed"],
        effects=[EffectSpec.parse(e) for e in SIM["effects"]],
    )
    return simulate(cfg)


@functools.cache
def golden_run(method: str):
    """The golden run of ``method`` (one torch thread: reductions in a fixed order), computed once per process:
    the golden test and the pipeline tests of the auto run share it, so callers must not change it (copy first)."""
    from torchcal._threads import torch_threads
    from torchcal.pipeline import Options, calibrate

    with torch_threads(1):
        return calibrate(SIM["robot"], campaign().train, Options.of(method=method, seed=SIM["seed"], **CASES[method]))


def golden_report(method: str) -> dict:
    """The report of the golden run of ``method``."""
    from torchcal._threads import torch_threads
    from torchcal.report.rundir import build_report

    with torch_threads(1):
        return json.loads(json.dumps(build_report(golden_run(method))))


def path(method: str) -> Path:
    return HERE / f"report_{method.replace('+', '_')}.json"


def main(argv: list[str]) -> int:
    for method in argv or list(CASES):
        path(method).write_text(json.dumps(golden_report(method), indent=1) + "\n", encoding="utf-8")
        print(f"wrote {path(method)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
