"""A probe for issue 46 item 3's remaining gap: would a level of what the model leaves unexplained that varies with
the pose make a kinematic run's sigma less wide where its errors grow with one joint (an unmodelled
transmission-ratio error)? Not in the package: ``torchcal.estimate.trust`` keeps one level per axis.

The campaign's training rows are calibrated (``method``) with calibrate's own held-out split, whose rows measure,
as :func:`torchcal.estimate.trust.fit_trust` does, the scale ``k`` that puts 99 % of them within 3 sigma over two
levels: ``constant`` (the package's per-axis moment estimate) and ``by_pose`` (the held-out rows' squared errors
less the parameters' and the noise's variance, regressed by ridge least squares on ``1, q_j^2, cos q_j, sin q_j``
of every joint, floored at 0). Both are then judged on the test rows: the share whose three ``|error| / sigma`` are
all <= 3 and the median ``|error| / sigma``.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch

from torchcal.data import Measurements, read_measurements
from torchcal.effects import Context
from torchcal.estimate.trust import COVERED, base_variance
from torchcal.pipeline import Options, calibrate, holdout_split
from torchcal.report.rundir import write_run
from torchcal.use.rundir import load_covariance, load_model

HOLDOUT, SEED, RIDGE = 0.2, 0, 1e-3


def _features(q: torch.Tensor) -> torch.Tensor:
    return torch.cat([torch.ones(len(q), 1, dtype=q.dtype), q.square(), q.cos(), q.sin()], 1)


def run(folder: Path, robot: str = "ur5", method: str = "kinematic") -> dict:
    """The module docstring's comparison on ``folder`` (``train.csv``, ``test.csv``)."""
    train, test = read_measurements(folder / "train.csv"), read_measurements(folder / "test.csv")
    with tempfile.TemporaryDirectory() as tmp:
        rd = write_run(
            calibrate(robot, train, Options.of(method=method, seed=SEED, holdout=HOLDOUT, trajectory=False)),
            Path(tmp) / "run",
        )
        model, meta = load_model(rd)
        cov = load_covariance(rd, model)
    noise = tuple((meta.get("trust") or {}).get("noise_m") or (15e-6,) * 3)
    split = holdout_split(train, HOLDOUT, SEED, trajectory=False)
    held = train.subset(torch.sort(split.held).values)

    def parts(m: Measurements):
        ctx = Context.from_measurements(m, trajectory=False)
        with torch.no_grad():
            return (model(ctx) - m.p).cpu(), base_variance(model, ctx, cov, noise).cpu(), m.q.cpu()

    (eh, vh, qh), (et, vt, qt) = parts(held), parts(test)
    u = (eh.square() - vh).mean(0).clamp(min=0)
    X, y = _features(qh), (eh.square() - vh).mean(1, keepdim=True)
    A = X.T @ X
    b = torch.linalg.solve(A + RIDGE * A.diagonal().mean() * torch.eye(len(A), dtype=A.dtype), X.T @ y)
    levels = {
        "constant": (u.expand_as(vh), u.expand_as(vt)),
        "by_pose": ((X @ b).clamp(min=0).expand_as(vh), (_features(qt) @ b).clamp(min=0).expand_as(vt)),
    }
    out = {"campaign": folder.name, "method": method, "n_holdout": held.n, "n_test": test.n}
    for name, (lh, lt) in levels.items():
        z = eh.abs() / (vh + lh).sqrt()
        k = max(1.0, float(torch.quantile(z.amax(dim=1), COVERED)) / 3.0)
        zt = et.abs() / ((vt + lt).sqrt() * k)
        out[name] = {
            "scale": k,
            "within_3sigma": float((zt <= 3.0).all(dim=1).double().mean()),
            "median_ratio": float(zt.median()),
        }
    return out
