"""Does ``sx, sy, sz`` cover the error? Coverage of the predictive sigma on real held-out rows.

A UR10 series (Landgraf et al.) is split in two: ``grouped``, a seeded 20 % of its revisit groups held out (revisits
of a configuration stay on one side); or ``q2-central``, training on the central 70 % of q2's range and testing on
the rest (every test row beyond the calibrated region). The training part is calibrated (default method), the run
directory written and loaded back as ``predict`` loads it, and each test row predicted with its ``sx, sy, sz`` and
its ``model`` (:func:`torchcal.use.rundir.row_trust`). The measures: the share of test rows whose three
``|error| / sigma`` are all <= 3 (a Gaussian: 0.99) and the median ``|error| / sigma`` over rows and axes (a
Gaussian: 0.67); beside them the same for the sigma of the parameters and the learned posterior alone (before
``torchcal`` measured what a run leaves unexplained).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch

from experiments.ipa_series import series_file
from torchcal.data import Measurements, read_ipa
from torchcal.effects import Context
from torchcal.estimate.covariance import combined_std
from torchcal.pipeline import Options, calibrate
from torchcal.report.rundir import write_run
from torchcal.robot import load_robot
from torchcal.stats import revisit_groups
from torchcal.use.rundir import MODEL_NAMES, load_covariance, load_model, predict_with, row_trust

SPLITS = ("grouped", "q2-central")


def split(data: Measurements, kind: str, seed: int = 0, held: float = 0.2, share: float = 0.7):
    """Training and test row indices of ``data`` (module docstring)."""
    if kind == "grouped":
        labels = revisit_groups(data.q)
        groups = torch.unique(labels)
        g = torch.Generator().manual_seed(seed)
        chosen = groups[torch.randperm(len(groups), generator=g)[: max(1, round(held * len(groups)))]]
        test = torch.isin(labels, chosen)
    elif kind == "q2-central":
        q = data.q[:, 1]
        lo, hi = float(q.min()), float(q.max())
        mid, half = (lo + hi) / 2, share * (hi - lo) / 2
        test = (q < mid - half) | (q > mid + half)
    else:
        raise ValueError(f"split must be one of {SPLITS}, got {kind!r}")
    return torch.nonzero(~test).flatten(), torch.nonzero(test).flatten()


def coverage(e: torch.Tensor, sigma: torch.Tensor) -> dict:
    """The share of rows whose three ``|e| / sigma`` are all <= 3, and the median over rows and axes."""
    z = e.abs() / sigma
    return {"share_within_3": float((z.amax(dim=1) <= 3).double().mean()), "median_ratio": float(z.median())}


def run(path: Path, series: str, kind: str, *, seed: int = 0, method: str = "auto") -> dict:
    """Calibrate the training part, predict the test part as ``predict`` does; the coverage (module docstring)."""
    data = read_ipa(series_file(path, series))
    tr, te = split(data, kind, seed)
    train, test = data.subset(tr), data.subset(te)
    result = calibrate(load_robot("ur10"), train, Options(method=method, seed=seed))
    with tempfile.TemporaryDirectory() as tmp:
        out = write_run(result, Path(tmp) / "run")
        model, meta = load_model(out)
        ctx = Context.from_measurements(test, trajectory=False)
        rt = row_trust(out, model, meta, ctx)
        p = predict_with(model, meta, test)
        if rt.geometric is not None and bool(rt.which.any()):
            rows = torch.nonzero(rt.which).flatten()
            p[rows] = predict_with(rt.geometric, meta, test.subset(rows))
        before = combined_std(model, ctx, load_covariance(out, model))
        report_trust = meta.get("trust")
    e = p - test.p
    return {
        "series": series,
        "split": kind,
        "method": method,
        "seed": seed,
        "n_train": len(tr),
        "n_test": len(te),
        "rows_beyond_region": int((rt.extrapolation > 0).sum()),
        "rows_geometric": int((rt.which == MODEL_NAMES.index("geometric")).sum()),
        # which model predicted the test rows, and what the run chose for beyond its region (torchcal.pipeline.beyond)
        "models": {name: int((rt.which == k).sum()) for k, name in enumerate(MODEL_NAMES)},
        "beyond": meta.get("beyond"),
        "rmse_mm": float(e.norm(dim=1).square().mean().sqrt()) * 1e3,
        "median_sigma_mm": float(rt.sigma.median()) * 1e3,
        **coverage(e, rt.sigma),
        "trust": report_trust,
        "before": {"median_sigma_mm": float(before.median()) * 1e3, **coverage(e, before)}
        if before is not None
        else None,
    }


def probe_check(path: Path, series: str, *, seed: int = 0, per_side: int = 25) -> dict:
    """Which model predicts just beyond the data: the default method and the kinematic calibration on the whole
    series (positions only), both probed on training poses with one joint pushed 0.1-0.6 rad beyond its range
    (:func:`experiments.edge_probe.probes`).

    Returns:
        A JSON-ready dict: each run's largest predictive sigma ``|(sx, sy, sz)|`` on the probes [mm], the largest
        difference of their predictions [mm], and the probes that ``predict`` gives to the kinematic calibration.
    """
    from experiments.edge_probe import probes
    from torchcal.use.rundir import trust

    data = read_ipa(series_file(path, series)).without_orientation()
    robot = load_robot("ur10")
    out: dict = {"series": series, "seed": seed}
    with tempfile.TemporaryDirectory() as tmp:
        runs = {}
        for method in ("auto", "kinematic"):
            result = calibrate(robot, data, Options(method=method, seed=seed))
            runs[method] = write_run(result, Path(tmp) / method)
            if method == "auto":
                probe, _, _ = probes(data.subset(result.train_idx), robot.limits, per_side, seed)
                ctx = Context.from_measurements(probe, trajectory=False)
        pred, sigma = {}, {}
        for method, run_dir in runs.items():
            model, meta = load_model(run_dir)
            pred[method] = predict_with(model, meta, probe)
            sigma[method] = trust(run_dir, model, ctx)[0].norm(dim=1)
            if method == "auto":
                which = row_trust(run_dir, model, meta, ctx).which
    out.update(
        n_probes=probe.n,
        max_sigma_default_mm=float(sigma["auto"].max()) * 1e3,
        max_sigma_kinematic_mm=float(sigma["kinematic"].max()) * 1e3,
        max_difference_mm=float((pred["auto"] - pred["kinematic"]).norm(dim=1).max()) * 1e3,
        rows_geometric=int((which == MODEL_NAMES.index("geometric")).sum()),
    )
    return out
