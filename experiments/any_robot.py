"""Robots that are not UR-like (issue 25): simulated campaigns of each, calibrated with the default method.

Cases (``CASES``): a UR10 on a linear track (a prismatic axis), a UR10 on a lifting column whose two segments follow
one reading (prismatic, one a URDF mimic joint; the description loaded as a vendor writes it), a parallelogram
industrial robot whose controller readings are not its model joints (a ``readings:`` block: q3 = -(J2 + J3),
reversed wrist) and a 7-axis arm with a cable differential in its wrist and no link masses. Each is simulated with
the effects and ratio errors its kind of cell has, and once clean.

Per case: what the loop named; the error on the campaign's test poses of the final model, of the true structure
(the geometric fit with exactly the simulated named effects, refitted on the same training poses) and of the
simulation's own model (the noise floor); the simulated ratio errors and scalar effect parameters against their
estimates, in standard deviations of the final fit. For the clean campaign: what it named (nothing, when the loop
holds its level) and the same errors.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import torch

from torchcal.diagnose.candidates import candidates
from torchcal.effects import Context
from torchcal.effects.joint import RegionForm
from torchcal.estimate.fit import errors, solve
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import build_report
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.stats import rmse

DATA = Path(__file__).resolve().parents[1] / "tests"

#: name -> robot, effects, ratio errors of its readings map, poses
CASES: dict[str, dict] = {
    "track": {"robot": "ur10_track", "effects": ["compliance:3=50um", "cyclic:4=30um"], "ratios": {}},
    "column": {
        "robot": str(DATA / "robot" / "data" / "column_ur10.urdf"),
        "effects": ["compliance:3=50um"],
        "ratios": {},
    },
    "parallelogram": {
        "robot": str(DATA / "robot" / "data" / "fanuc_like.yaml"),
        "effects": ["compliance:2=60um", "coupling:5<-4=60um"],
        "ratios": {"readings.c3_3": 2e-3},
    },
    "arm7_differential": {
        "robot": str(DATA / "robot" / "data" / "arm7_differential.yaml"),
        "effects": ["compliance:4=50um"],
        "ratios": {"readings.c6_6": 2e-3},
    },
}


def _true_structure(run, truth: dict):
    """The final run's geometric stage with exactly the simulated named effects, refitted on its training poses;
    None where an effect has no candidate of that name (it was skipped for these poses)."""
    train = run.train
    ctx = Context.from_measurements(train, trajectory=run.trajectory)
    menu = {c.name: c for c in candidates(run.robot, ctx)[0]}
    model = copy.deepcopy(run.stage("geometric").model)
    for e in truth["effects"]:
        name = f"{e['kind']}:{e['joint']}" + (f"<-{e['source']}" if e.get("source") else "")
        if name not in menu:
            return None
        eff = menu[name].make()
        if isinstance(eff, RegionForm):
            eff.set_region(train.q)
        model.add(eff)
    ida = next((f.identifiability for f in run.fits if f.stage == "geometric"), None)
    solve(
        model,
        train,
        ("geometry", "instrument", "tool"),
        run.options.fit,
        "true structure",
        trajectory=run.trajectory,
        effects=True,
        identifiability=ida,
    )
    return model


def _z_scores(report: dict, truth: dict) -> dict:
    """Simulated ratio errors and scalar effect parameters against the final fit's estimates, in its sigmas."""
    out = {}
    est = {p["name"]: p for p in report["parameters"]["estimated"]}
    for name, value in truth.get("readings", {}).get("ratio_errors", {}).items():
        p = est.get(name.removeprefix("readings.") if name not in est else name) or est.get(name)
        if p is not None and p.get("std"):
            out[name] = (p["correction"] - value) / p["std"]
    found = {(e["kind"], e["joint"]): e for e in report["effects"]}
    for e in truth["effects"]:
        got = found.get((e["kind"], e["joint"]))
        c = got["params"].get("c") if got else None
        if isinstance(c, dict) and c.get("std") and "c" in e.get("params", {}):
            out[f"{e['kind']}:{e['joint']}.c"] = (c["value"] - e["params"]["c"]) / c["std"]
    return out


def run_case(name: str, *, seed: int = 1, poses: int = 300, test_poses: int = 200, clean: bool = False) -> dict:
    case = CASES[name]
    effects = [] if clean else [EffectSpec.parse(e) for e in case["effects"]]
    cfg = SimConfig(
        robot=case["robot"],
        poses=poses,
        test_poses=test_poses,
        seed=seed,
        effects=effects,
        ratio_errors={} if clean else dict(case["ratios"]),
    )
    c = simulate(cfg)
    t0 = time.perf_counter()
    run = calibrate(case["robot"], c.train, Options(seed=seed))
    seconds = time.perf_counter() - t0
    report = build_report(run)

    def test_mm(model) -> float:
        return rmse(errors(model, c.test, False)) * 1e3

    true = _true_structure(run, c.truth)
    out = {
        "case": name,
        "clean": clean,
        "seed": seed,
        "robot": Path(case["robot"]).stem,
        "readings": run.robot.dof,
        "model_joints": run.robot.n_joints,
        "simulated": [] if clean else list(case["effects"]) + [f"{k}={v:g}" for k, v in case["ratios"].items()],
        "named": [e.get("name", e["kind"]) for e in report["effects"]],
        "seconds": round(seconds, 1),
        "test_final_mm": test_mm(run.model),
        "test_geometric_mm": test_mm(run.stage("geometric").model),
        "test_true_structure_mm": None if true is None else test_mm(true),
        "test_oracle_mm": test_mm(c.model),
        "z": _z_scores(report, c.truth),
    }
    if true is not None:
        out["ratio_to_true_structure"] = out["test_final_mm"] / out["test_true_structure_mm"]
    return out


def run(cases: list[str], seeds: list[int], poses: int = 300, clean: bool = True) -> dict:
    torch.set_num_threads(1)
    rows = []
    for name in cases:
        for seed in seeds:
            rows.append(run_case(name, seed=seed, poses=poses))
            if clean:
                rows.append(run_case(name, seed=seed, poses=poses, clean=True))
    dirty = [r for r in rows if not r["clean"] and "ratio_to_true_structure" in r]
    return {
        "rows": rows,
        "worst_ratio_to_true_structure": max((r["ratio_to_true_structure"] for r in dirty), default=None),
        "largest_abs_z": max((abs(z) for r in rows for z in r["z"].values()), default=None),
        "clean_named": sorted({n for r in rows if r["clean"] for n in r["named"]}),
    }
