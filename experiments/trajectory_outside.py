"""The integrated method on outside-style trajectories, judged on the continuation of each path.

:mod:`experiments.trajectories` uses the project's own path families and field
(:mod:`torchcal.sim.campaign`); here the campaigns come from :func:`torchcal.sim.outside.simulate_outside_trajectory`,
whose multi-sine path and formula field share neither. For each seed and field kind: geometry alone
(``--method kinematic``) and ``--method integrated`` (its default engine) calibrated on the training part, both
judged on the continuation, their ratio, the 2-sigma coverage of the predicted standard deviation (what ``predict``
writes as ``sx, sy, sz``), the candidate chosen on validation and the validation table from the report (the
evidence to tell why a candidate that won validation fails on the continuation).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from torchcal._threads import torch_threads
from torchcal.data import Measurements
from torchcal.effects import Context
from torchcal.effects.region import coverage, predictive_sigma
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate
from torchcal.sim.campaign import write_campaign
from torchcal.sim.outside import OutsideTrajectory, simulate_outside_trajectory
from torchcal.stats import rmse


def _rmse_mm(model, data: Measurements) -> float:
    return rmse(errors(model, data, trajectory=True)) * 1e3


def _residuals(model, data: Measurements) -> torch.Tensor:
    """Prediction minus measurement per tracker axis ``(N, 3)`` [m]."""
    with torch.no_grad():
        return model(Context.from_measurements(data, trajectory=True)) - data.p


def novelty(train_q: torch.Tensor, test_q: torch.Tensor) -> dict:
    """How far the continuation leaves the training path: the distance [rad] in joint space from each continuation
    sample to its nearest training sample, median and 90th percentile, and the share farther than 0.3 rad."""
    d = torch.cdist(test_q, train_q).min(dim=1).values
    return {
        "median_rad": float(d.median()),
        "p90_rad": float(torch.quantile(d, 0.9)),
        "share_beyond_0p3_rad": float((d > 0.3).to(d.dtype).mean()),
    }


def _selection(run) -> dict:
    """The integrated method's selection evidence (from the kept effect or the rejection), or an empty dict."""
    for r in list(run.effects) + list(run.rejections):
        if r.name == "integrated" and r.evidence.get("selection"):
            return r.evidence["selection"]
    return {}


def evaluate(spec: OutsideTrajectory, out: str | Path | None = None, default_method: bool = False) -> dict:
    """Simulate one campaign of ``spec`` and compare geometry alone and ``integrated`` on its continuation.

    Args:
        spec: the campaign.
        out: where to write the campaign's ``train.csv``, ``test.csv``, ``truth.json`` (None: nowhere).
        default_method: also the default method (``auto``, what a user who names no method gets) on the same
            continuation: ``auto_mm``, ``auto_ratio`` (over the kinematic calibration on the training part,
            ``geometry_training_part_mm``: auto writes no refit), ``auto_effects`` and its held-out guard.

    Returns:
        A JSON-ready row: the campaign, the continuation RMSE [mm] of both, ``ratio`` (integrated over geometry),
        ``coverage_2sigma`` on the continuation, ``chosen`` and the validation table.
    """
    c = simulate_outside_trajectory(spec)
    if out is not None:
        write_campaign(c, out)
    row: dict = {
        "seed": spec.seed,
        "field": spec.field,
        "width": spec.width,
        "size_mm": spec.size * 1e3,
        "train": c.train.n,
        "test": c.test.n,
        "continuation_novelty": novelty(c.train.q, c.test.q),
    }
    t0 = time.perf_counter()
    kin = calibrate(spec.robot, c.train, Options(method="kinematic", seed=0, refit=True))
    row["geometry_mm"] = _rmse_mm(kin.model, c.test)
    row["geometry_s"] = time.perf_counter() - t0
    # the last 20 % of the training file, held out by calibrate (the same time-ordered split for both methods)
    row["geometry_internal_holdout_mm"] = kin.stages[-1].rmse * 1e3
    t0 = time.perf_counter()
    run = calibrate(spec.robot, c.train, Options(method="integrated", seed=0))
    row["integrated_s"] = time.perf_counter() - t0
    row["integrated_mm"] = _rmse_mm(run.model, c.test)
    row["ratio"] = row["integrated_mm"] / row["geometry_mm"]
    row["integrated_internal_holdout_mm"] = run.stages[-1].rmse * 1e3
    sigma = predictive_sigma(run.model, c.test.q)
    row["coverage_2sigma"] = None if sigma is None else coverage(_residuals(run.model, c.test), sigma)
    sel = _selection(run)
    row["chosen"] = sel.get("chosen") if run.effects else "geometry alone"
    row["gate_length"] = run.effects[-1].params.get("support_gate_length") if run.effects else None
    row["validation_test"] = sel.get("test")
    row["validation"] = [
        {k: v for k, v in cand.items() if k in ("candidate", "validation_rmse_mm", "gate_length", "failed")}
        | (
            {"worst_left_out_ratio": max(cand["leave_one_piece_out_ratios"])}
            if "leave_one_piece_out_ratios" in cand
            else {}
        )
        for cand in sel.get("candidates", [])
    ]
    if run.effects:
        ev = run.effects[-1].evidence.get("predictive_sigma", {})
        row["coverage_2sigma_validation"] = ev.get("coverage_2sigma_validation")
        row["coverage_2sigma_holdout"] = ev.get("coverage_2sigma_holdout")
    if default_method:
        t0 = time.perf_counter()
        auto = calibrate(spec.robot, c.train, Options(seed=0))
        row["auto_s"] = time.perf_counter() - t0
        row["auto_mm"] = _rmse_mm(auto.model, c.test)
        # against the simpler method it replaces as a user runs it: the kinematic calibration on the training part
        # (the geometric stage of the refitted one above), as auto writes no refit
        row["geometry_training_part_mm"] = _rmse_mm(kin.stage("geometric").model, c.test)
        row["auto_ratio"] = row["auto_mm"] / row["geometry_training_part_mm"]
        row["auto_effects"] = [r.name for r in auto.effects]
        row["auto_holdout_guard"] = auto.holdout_guard
    return row


def table(
    seeds,
    fields,
    *,
    size: float = 1e-4,
    width: int = 29,
    samples: int = 7342,
    periods: tuple[float, float] | None = None,
    out: str | Path | None = None,
    default_method: bool = False,
) -> list[dict]:
    """:func:`evaluate` for every seed and field kind (one torch thread), one campaign at a time.

    ``size`` [m], ``width``, ``samples`` and ``periods`` [samples] as in :class:`OutsideTrajectory`; ``out``: a
    folder that gets one sub-folder ``<field>-s<seed>`` per campaign (None: nothing written); ``default_method``:
    the default method too (:func:`evaluate`).
    """
    rows = []
    base = OutsideTrajectory(size=size, width=width, samples=samples, periods=periods)
    with torch_threads(1):
        for seed in seeds:
            for field in fields:
                spec = replace(base, seed=seed, field=field)
                rows.append(evaluate(spec, None if out is None else Path(out) / f"{field}-s{seed}", default_method))
    return rows


def summary(rows: list[dict]) -> dict:
    """Worst and median ratio, the campaigns where integrated is worse than geometry alone, and those whose
    coverage lies outside 90-98 %."""
    ratios = sorted(r["ratio"] for r in rows)
    return {
        "campaigns": len(rows),
        "worst_ratio": ratios[-1] if ratios else None,
        "median_ratio": statistics.median(ratios) if ratios else None,
        # a relative 1e-6 above 1: a gate faded to geometry alone leaves rounding differences only
        "worse_than_geometry": [f"{r['field']}-s{r['seed']}" for r in rows if r["ratio"] > 1.0 + 1e-6],
        "coverage_outside_90_98": [
            f"{r['field']}-s{r['seed']}"
            for r in rows
            if r["coverage_2sigma"] is not None and not 0.90 <= r["coverage_2sigma"] <= 0.98
        ],
    }


def markdown(rows: list[dict]) -> str:
    """The rows as a Markdown table: continuation RMSE of both [mm], their ratio, 2-sigma coverage, the choice."""
    lines = [
        "| campaign | field | geometry alone [mm] | integrated [mm] | ratio | 2σ coverage | chosen on validation |",
        "|---|---|---|---|---|---|---|",
    ]
    shape = {"tanh": "6-{}-3 tanh", "fourier": "{} Fourier features", "product": "{} products", "additive": "{}/joint"}
    for r in rows:
        kind = shape.get(r["field"], "{}").format(r["width"]) if r["field"] != "none" else "no field"
        cov = "–" if r["coverage_2sigma"] is None else f"{100 * r['coverage_2sigma']:.1f} %"
        lines.append(
            f"| {r['field']}-s{r['seed']} | {kind}, {r['size_mm']:g} mm | {r['geometry_mm']:.4f} | "
            f"{r['integrated_mm']:.4f} | {r['ratio']:.3f} | {cov} | {r['chosen']} |"
        )
    if any("auto_mm" in r for r in rows):
        lines += [
            "",
            "| campaign | kinematic, no refit [mm] | default (auto) [mm] | ratio | effects kept | held-out guard |",
            "|---|---|---|---|---|---|",
        ]
        for r in rows:
            if "auto_mm" in r:
                g = r["auto_holdout_guard"]
                guard = "-" if g is None else ("passed" if g["passed"] else f"stepped back to {g['kept_stage']}")
                lines.append(
                    f"| {r['field']}-s{r['seed']} | {r['geometry_training_part_mm']:.4f} | {r['auto_mm']:.4f} | "
                    f"{r['auto_ratio']:.3f} | "
                    f"{', '.join(r['auto_effects']) or 'none'} | {guard} |"
                )
    return "\n".join(lines)
