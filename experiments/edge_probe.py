"""Probe a calibration just outside its data: is the correction beyond the kinematic calibration bounded there?

A calibration is used where it was not measured. This experiment calibrates a measurement file twice, with the
default method and with ``kinematic``, and compares their predictions on *probes*: training poses with one joint
pushed ``delta`` beyond that joint's range in the file (``delta`` uniform in 0.1-0.6 rad, both sides of every
joint, within the joint's limits). The *correction* of a pose is the default's prediction minus the kinematic
calibration's; the measure is the largest correction on the probes over the largest on the training poses
(``ratio``: at most 2 is asked of a model that knows where it was fitted), with the probes' ``extrapolation``
(:meth:`torchcal.effects.MeasurementModel.extrapolation`) beside it.

:func:`home_split` is the other half: a grouped split (revisits of a configuration kept together) whose held-out
part holds a given pose (the data's home pose, outside the range of the rest), calibrated on the training part and
judged on the held-out rows, the home pose by itself.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from torchcal.data import Measurements, read_ipa, read_measurements
from torchcal.effects import Context
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate
from torchcal.robot import load_robot
from torchcal.stats import revisit_groups

F64 = torch.float64


def probes(
    train: Measurements, limits: torch.Tensor, per_side: int, seed: int, lo: float = 0.1, hi: float = 0.6
) -> tuple[Measurements, torch.Tensor, torch.Tensor]:
    """Training poses with one joint pushed beyond its range in ``train``.

    Args:
        train: the measurements the calibration saw.
        limits: ``(dof, 2)`` joint limits; a probe beyond them is not made.
        per_side: probes per joint and side.
        seed: of the random poses and distances.
        lo, hi: the distance beyond the range [rad], uniform in between.

    Returns:
        The probes (the rows' other columns copied), their joint (0-based) and their distance beyond the range.
    """
    g = torch.Generator().manual_seed(seed)
    q = train.q
    rows, joints, deltas = [], [], []
    for j in range(q.shape[1]):
        q_lo, q_hi = float(q[:, j].min()), float(q[:, j].max())
        for side, edge in ((-1.0, q_lo), (1.0, q_hi)):
            d = lo + (hi - lo) * torch.rand(per_side, generator=g, dtype=F64)
            target = edge + side * d
            ok = (target >= limits[j, 0]) & (target <= limits[j, 1])
            idx = torch.randint(len(q), (per_side,), generator=g)[ok]
            rows.append(idx)
            joints.append(torch.full((len(idx),), j))
            deltas.append(torch.stack([target[ok], d[ok]], 1))
    idx, joint, td = torch.cat(rows), torch.cat(joints), torch.cat(deltas)
    out = train.subset(idx)
    qp = out.q.clone()
    qp[torch.arange(len(idx)), joint] = td[:, 0]
    probe = Measurements(
        q=qp, p=out.p, t=out.t, temperature=out.temperature, sigma=out.sigma, meta=out.meta, source=out.source
    )
    return probe, joint, td[:, 1]


def load(path: Path, fmt: str = "csv") -> Measurements:
    """A measurement file: the contract's CSV (``csv``) or an ipa-robot-accuracy series file (``ipa``)."""
    return read_ipa(path) if fmt == "ipa" else read_measurements(path)


def run(path: Path, robot: str, *, seed: int = 0, per_side: int = 25, method: str = "auto", fmt: str = "csv") -> dict:
    """Calibrate ``path`` with ``method`` and with ``kinematic`` and probe both (module docstring).

    Returns:
        A JSON-ready dict: the effects kept, the largest correction on the training poses and on the probes [mm], their
        ratio, the probes whose correction exceeds the training poses' largest, and the probes' extrapolation.
    """
    data = load(path, fmt)
    rb = load_robot(robot)
    runs = {m: calibrate(rb, data, Options(method=m, seed=seed)) for m in (method, "kinematic")}
    train = data.subset(runs[method].train_idx)
    probe, joint, delta = probes(train, rb.limits, per_side, seed)
    trajectory = runs[method].trajectory

    def correction(m: Measurements) -> torch.Tensor:
        ctx = Context.from_measurements(m, trajectory=trajectory)
        with torch.no_grad():
            return (runs[method].model(ctx) - runs["kinematic"].model(ctx)).norm(dim=1)

    c_train, c_probe = correction(train), correction(probe)
    peak = float(c_train.max())
    worst = int(c_probe.argmax())
    ext = runs[method].model.extrapolation(probe.q)
    return {
        "data": str(path),
        "robot": robot,
        "method": method,
        "effects": [e.get("name", e.get("kind")) for e in runs[method].effects_report],
        "n_train": len(train.q),
        "n_probes": len(probe.q),
        "max_correction_train_mm": peak * 1e3,
        "max_correction_probes_mm": float(c_probe.max()) * 1e3,
        "ratio": float(c_probe.max()) / peak if peak > 0 else math.nan,
        "probes_above_train_max": int((c_probe > peak).sum()),
        "worst_probe": {"joint": int(joint[worst]) + 1, "beyond_rad": float(delta[worst])},
        # how the correction falls off with the distance beyond the range: the largest in each band [mm]
        "max_correction_by_distance_mm": {
            f"{a}-{b}": float(c_probe[(ext >= a) & (ext < b)].max()) * 1e3
            if bool(((ext >= a) & (ext < b)).any())
            else None
            for a, b in ((0.1, 0.2), (0.2, 0.4), (0.4, 0.61))
        },
        "extrapolation_min": float(ext.min()),
        "extrapolation_max": float(ext.max()),
    }


def home_split(
    path: Path,
    robot: str,
    home: list[float],
    *,
    seed: int = 1,
    held: float = 0.2,
    method: str = "auto",
    fmt: str = "csv",
) -> dict:
    """Calibrate on a grouped split that holds ``home`` out; errors of ``method`` and ``kinematic`` there.

    Revisits of a configuration (:func:`torchcal.stats.revisit_groups`) stay on one side; a seeded share ``held``
    of the groups is held out, the group nearest ``home`` [rad] always among them. Each method is then calibrated
    on the training rows alone (its own internal hold-out inside them) and predicts the held-out rows.

    Returns:
        A JSON-ready dict: the sizes, the home row's distance beyond the training range, and per method the
        held-out RMSE, median and max and the error at the home pose [mm].
    """
    data = load(path, fmt)
    rb = load_robot(robot)
    labels = revisit_groups(data.q)
    groups = torch.unique(labels)
    g = torch.Generator().manual_seed(seed)
    chosen = groups[torch.randperm(len(groups), generator=g)[: max(1, round(held * len(groups)))]]
    target = torch.tensor(home, dtype=data.q.dtype)
    home_row = int((data.q - target).norm(dim=1).argmin())
    test_mask = torch.isin(labels, chosen) | (labels == labels[home_row])
    train, test = data.subset(torch.nonzero(~test_mask)[:, 0]), data.subset(torch.nonzero(test_mask)[:, 0])
    at_home = int(torch.nonzero(torch.nonzero(test_mask)[:, 0] == home_row)[0, 0])
    out = {
        "data": str(path),
        "robot": robot,
        "seed": seed,
        "n_train": len(train.q),
        "n_test": len(test.q),
        "home_q": [float(v) for v in data.q[home_row]],
        "home_beyond_training_range_rad": 0.0,
        "methods": {},
    }
    for m in (method, "kinematic"):
        r = calibrate(rb, train, Options(method=m, seed=seed))
        e = errors(r.model, test, r.trajectory) * 1e3
        out["home_beyond_training_range_rad"] = float(r.model.extrapolation(data.q[home_row : home_row + 1])[0])
        out["methods"][m] = {
            "effects": [x.get("name", x.get("kind")) for x in r.effects_report]
            + [type(x).__name__ for x in r.model.effects if x.kind == "learned"],
            "rmse_mm": float(e.square().mean().sqrt()),
            "median_mm": float(e.median()),
            "max_mm": float(e.max()),
            "home_mm": float(e[at_home]),
        }
    return out
