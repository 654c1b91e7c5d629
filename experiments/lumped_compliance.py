"""Compliance of a robot without link masses (issue 25): simulated campaigns of the DH-only 7-axis arm.

Per seed: a campaign with lumped compliances (``--effects``, default joints 2 and 4) and a clean one, both
calibrated by default (``auto``). For the first: the effects named, the held-out error on the test poses against the
true structure (the geometric fit plus the lumped forms of the simulated joints, refitted on the same training
poses), and each identifiable combination of the true moments (the modes whose probe displacement beyond the
geometry equals the truth's) against its estimate, in standard deviations of the fit. For the clean one: what it
named (nothing, when the loop holds its level).
"""

from __future__ import annotations

import copy
import time

import torch

from torchcal.effects import LumpedCompliance
from torchcal.effects.joint import geometric_span
from torchcal.estimate.fit import errors, solve
from torchcal.pipeline import Options, calibrate
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.stats import rmse

ROBOT = "arm7_dh"
GROUPS = ("geometry", "instrument", "tool")


def true_modes(robot, q: torch.Tensor, fitted: LumpedCompliance, truth: LumpedCompliance) -> torch.Tensor:
    """The modes of ``fitted``'s basis that move the probe beyond the geometry as ``truth`` does at ``q``
    ``(N, dof)`` (least squares over the poses) ``(r,)`` [rad]."""
    j = fitted.j
    with torch.no_grad():
        Y = robot.gravity_regressor(q)[:, j]
        _, Jq = robot.probe_jacobian(q)
        M = (Jq[:, :, j, None] * Y[:, None, :]).reshape(-1, Y.shape[1])
        span = geometric_span(robot, q)
        M = M - span @ (span.T @ M)
        beta = truth.basis @ truth.mode.detach()
        return torch.linalg.lstsq(M @ fitted.basis, (M @ beta)[:, None]).solution[:, 0]


def final_modes(run, eff: LumpedCompliance) -> list[tuple[float, float]]:
    """The modes of ``eff`` in the run's final model with their standard deviations from the run's last fit (the
    report's ``params`` hold them as fitted when the effect was accepted, before later effects joined)."""
    res = run.fits[-1].result
    pos = {n: i for i, n in enumerate(res.names)}
    return [
        (float(v), float(res.std[pos[f"{eff.label()}.mode[{i}]"]])) for i, v in enumerate(eff.mode.detach().tolist())
    ]


def run_seed(seed: int, effects: list[str], poses: int = 215, test_poses: int = 200) -> dict:
    """One campaign with ``effects`` and one clean campaign of the arm (module docstring); plain numbers [mm, s]."""
    specs = [EffectSpec.parse(e) for e in effects]
    c = simulate(SimConfig(robot=ROBOT, poses=poses, test_poses=test_poses, seed=seed, effects=specs))
    t0 = time.perf_counter()
    run = calibrate(ROBOT, c.train, Options(seed=seed))
    seconds = time.perf_counter() - t0
    train = c.train.subset(run.train_idx)
    geo = next(s for s in run.stages if s.name == "geometric")
    true = copy.deepcopy(geo.model)
    fitted = {e.joint: e for e in run.model.effects if isinstance(e, LumpedCompliance)}
    truth = {e.joint: e for e in c.model.effects}
    for s in specs:  # the true structure: the lumped form of every simulated joint, in its basis on these poses
        if s.joint in fitted:
            true.add(LumpedCompliance(s.joint, fitted[s.joint].basis))
        else:
            from torchcal.effects.joint import lumped_basis

            true.add(LumpedCompliance(s.joint, lumped_basis(geo.model.robot, train.q, s.joint)))
    ida = next(f.identifiability for f in run.fits if f.stage == "geometric")
    solve(true, train, GROUPS, run.options.fit, "true structure", trajectory=False, effects=True, identifiability=ida)
    report = {e.get("name", e["kind"]): e for e in run.effects_report}
    z = {}
    for joint, eff in fitted.items():
        if joint not in truth:
            continue
        m_true = true_modes(run.model.robot, train.q, eff, truth[joint])
        z[f"compliance:{joint}"] = [(v - float(t)) / s for (v, s), t in zip(final_modes(run, eff), m_true)]
    clean = simulate(SimConfig(robot=ROBOT, poses=poses, test_poses=test_poses, seed=seed))
    run_clean = calibrate(ROBOT, clean.train, Options(seed=seed))
    test_loop, test_true = rmse(errors(run.model, c.test, False)), rmse(errors(true, c.test, False))
    return {
        "seed": seed,
        "effects": list(effects),
        "named": sorted(report),
        "modes": {k: len(v) for k, v in z.items()},
        "test_loop_mm": test_loop * 1e3,
        "test_true_structure_mm": test_true * 1e3,
        "test_geometric_mm": rmse(errors(geo.model, c.test, False)) * 1e3,
        "ratio": test_loop / test_true,
        "max_abs_z": max((abs(v) for zs in z.values() for v in zs), default=float("nan")),
        "z": z,
        "clean_named": [e.get("name", e["kind"]) for e in run_clean.effects_report],
        "seconds": seconds,
    }


def run(seeds: int, first_seed: int, effects: list[str], poses: int = 215) -> dict:
    rows = [run_seed(first_seed + i, effects, poses) for i in range(seeds)]
    return {
        "robot": ROBOT,
        "poses": poses,
        "effects": effects,
        "named_right": sum(sorted(r["named"]) == sorted(s.split("=")[0] for s in effects) for r in rows),
        "worst_ratio": max(r["ratio"] for r in rows),
        "worst_abs_z": max(r["max_abs_z"] for r in rows),
        "clean_named_anything": sum(bool(r["clean_named"]) for r in rows),
        "runs": len(rows),
        "rows": rows,
    }
