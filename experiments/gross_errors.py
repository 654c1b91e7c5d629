"""Gross errors injected into a simulated campaign: does the calibration find them and stay accurate?

Used by ``scripts/gross_errors.py`` and the end-to-end tests of :mod:`torchcal.estimate.robust`. A trial
simulates a campaign, calibrates the clean training file, then the same file with gross errors injected
(rows shifted by ``size`` in random directions, or rows written in millimetres), and compares both on the
campaign's separate, clean test file.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from torchcal.data import Measurements
from torchcal.estimate.fit import errors
from torchcal.pipeline import CalibrationRun, Options, calibrate
from torchcal.sim import SimConfig, simulate

Tensor = torch.Tensor
F64 = torch.float64
MODES = ("shift", "mm")


def contaminate(
    m: Measurements, rows: Tensor, mode: str = "shift", size: float = 0.01, generator: torch.Generator | None = None
) -> Measurements:
    """A copy of ``m`` with gross errors in ``rows``.

    Args:
        rows: row indices ``(k,)``.
        mode: ``shift``: each row's position moved by ``size`` [m] in a random direction; ``mm``: the row's
            position (and its sx, sy, sz) 1000 times too large, as a row typed in millimetres in a file in metres.
        generator: for the directions (default seed 0).
    """
    if mode not in MODES:
        raise ValueError(f"mode '{mode}' is not one of {', '.join(MODES)}")
    g = generator or torch.Generator().manual_seed(0)
    p = m.p.clone()
    sigma = None if m.sigma is None else m.sigma.clone()
    if mode == "shift":
        u = torch.randn(len(rows), 3, generator=g, dtype=F64)
        p[rows] += size * u / u.norm(dim=-1, keepdim=True)
    else:
        p[rows] *= 1000.0
        if sigma is not None:
            sigma[rows] *= 1000.0
    return replace(m, p=p, sigma=sigma)


def _rmse(e: Tensor) -> float:
    return float(e.square().mean().sqrt()) if len(e) else float("nan")


def _rejected(run: CalibrationRun) -> tuple[set[int], set[int]]:
    """Data-row indices rejected from the training and from the held-out rows."""
    sc = run.screening
    if sc is None:
        return set(), set()
    line_to_row = {int(line): i for i, line in enumerate(run.data.lines)}
    return ({line_to_row[r.line] for r in sc.training.rejected}, {line_to_row[r.line] for r in sc.holdout.rejected})


def gross_error_trial(
    seed: int = 0,
    *,
    mode: str = "shift",
    fraction: float = 0.05,
    count: int | None = None,
    size: float = 0.01,
    where: str = "all",
    method: str = "kinematic",
    poses: int = 800,
    test_poses: int = 200,
    robot: str = "ur5",
    clean_run: CalibrationRun | None = None,
    campaign=None,
) -> dict:
    """Calibrate a clean and a contaminated copy of a simulated training file; compare on the clean test file.

    Args:
        seed: campaign seed (the contamination's rows and directions follow from it).
        mode: see :func:`contaminate`.
        fraction: share of the rows to contaminate (ignored when ``count`` is given).
        count: number of rows to contaminate.
        size: shift [m] (mode ``shift``).
        where: ``all`` rows of the file, or only the ``training`` or ``holdout`` rows of the calibration's split.
        method: calibration method.
        clean_run, campaign: reuse a clean calibration and its campaign (tests calibrate once).

    Returns:
        A JSON-ready dict: test-file RMSE [mm] clean and contaminated and their ratio, held-out RMSE [mm],
        the rows contaminated and rejected, found and false-rejection rates.
    """
    opts = Options(method=method, seed=0)
    c = campaign or simulate(SimConfig(robot=robot, poses=poses, test_poses=test_poses, seed=seed))
    data = c.train
    clean = clean_run or calibrate(robot, data, opts)
    pool = {"all": torch.arange(data.n), "training": clean.train_idx, "holdout": clean.holdout_idx}[where]
    g = torch.Generator().manual_seed(int(seed) + 7919)
    k = int(count) if count is not None else max(1, int(round(fraction * len(pool))))
    bad = torch.sort(pool[torch.randperm(len(pool), generator=g)[:k]]).values
    dirty = contaminate(data, bad, mode, size, g)
    run = calibrate(robot, dirty, opts)
    rej_tr, rej_ho = _rejected(run)
    rejected, badset = rej_tr | rej_ho, set(bad.tolist())
    n_good = data.n - len(badset)
    e_clean = _rmse(errors(clean.model, c.test, trajectory=False))
    e_dirty = _rmse(errors(run.model, c.test, trajectory=False))
    return {
        "seed": seed,
        "mode": mode,
        "size_mm": size * 1e3 if mode == "shift" else None,
        "where": where,
        "method": method,
        "n_rows": data.n,
        "n_contaminated": len(badset),
        "test_rmse_clean_mm": e_clean * 1e3,
        "test_rmse_contaminated_mm": e_dirty * 1e3,
        "test_ratio": e_dirty / e_clean if e_clean > 0 else math.nan,
        "holdout_rmse_clean_mm": clean.stages[-1].rmse * 1e3,
        "holdout_rmse_contaminated_mm": run.stages[-1].rmse * 1e3,
        "found": len(rejected & badset),
        "found_rate": len(rejected & badset) / max(len(badset), 1),
        "false_rejections": len(rejected - badset),
        "false_rate": len(rejected - badset) / max(n_good, 1),
        "clean_rejections": len(set().union(*_rejected(clean))),
        "rejected_training_lines": sorted(int(data.lines[i]) for i in rej_tr),
        "rejected_holdout_lines": sorted(int(data.lines[i]) for i in rej_ho),
        "contaminated_lines": [int(data.lines[i]) for i in bad.tolist()],
        "hints": sorted(
            {r.hint.split(":")[0] for r in run.screening.training.rejected + run.screening.holdout.rejected if r.hint}
        )
        if run.screening is not None
        else [],
    }
