"""Adaptive geometry in the integrated ANN-EKF (Horvath & Neuner 2024, Sec. 4 "future work"): geometry and network
estimated together on a simulated, paper-like UR5 trajectory.

Setting: a continuous UR5 trajectory (7342 samples, the first 5874 filtered, the rest predicted without updates,
as in the paper's Sec. 3), DH biases of 0.1 mm / 0.01 deg on every free element, an unknown tracker pose and lever
arm, a smooth non-geometric field (a random 6-29-3 tanh network scaled to ``--field`` RMS at the probe), tracker
noise 15 um per axis and joint noise 0.0005 deg. The filter starts from the nominal geometry with the tracker pose
and lever arm of a rigid fit (:func:`torchcal.estimate.rigid.fit_instrument_and_tool`) and estimates, together
with a correction network of fixed random features (:func:`torchcal.filter.random_features`), the identifiable
geometric corrections (:class:`torchcal.filter.AdaptiveEKF`).

"true" is the simulated robot expressed in the identifiable parameters: the batch fit to noise-free, field-free
data from the true robot at the true joints (exact to ~1e-15 m), which moves the non-identifiable biases (d1,
theta1, d6, ...) into the tracker pose and the lever arm; ``bias`` is the raw simulated DH bias for comparison.
``z = (estimate - true) / std`` with ``std`` from the filter's covariance. The same filter without the network
(the geometry alone, i.e. a recursive kinematic calibration) is run for comparison. Held-out RMSE: the test-phase
prediction against the noise-free truth (the model's error; ``_meas`` against the measurements, noise included).

    python scripts/adaptive_geometry.py [--quick] [--field 0.3mm] [--seed 0] [--hidden 128] [--passes 1]
                                        [--misfit-mm 0] [--json]

With ``--json`` the last stdout line is ``{"parameters": n, "within_3sigma": k, "max_abs_z": .., "rmse_test_mm": ..,
"rmse_geometry_only_test_mm": .., "seconds": .., ...}``.
"""

from __future__ import annotations

import math
import time

import torch

from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.fit import place_instrument_and_tool
from torchcal.filter import AdaptiveConfig, AdaptiveEKF, random_features
from torchcal.robot import load_robot
from torchcal.sim import EffectSpec, SimConfig, simulate


def rmse_mm(e: torch.Tensor) -> float:
    return float(e.norm(dim=-1).square().mean().sqrt()) * 1e3


def _z(r, truth) -> torch.Tensor:
    """(estimate - true) / std of the geometric corrections and the instrument translation of the result ``r``."""
    return torch.cat(
        [
            (r.gamma - truth.gamma) / r.gamma_std,
            (r.instrument_translation - truth.instrument_translation) / r.instrument_translation_std,
        ]
    )


def _rows(res, truth, raw: dict, z_joint: torch.Tensor, z_alone: torch.Tensor) -> list[dict]:
    """One row per estimated parameter (mm and degrees): simulated bias, true value, estimate, std, z scores."""
    names = res.names + ["instrument.tx", "instrument.ty", "instrument.tz"]
    units = res.units + ["m"] * 3
    true = torch.cat([truth.gamma, truth.instrument_translation])
    est = torch.cat([res.gamma, res.instrument_translation])
    std = torch.cat([res.gamma_std, res.instrument_translation_std])
    rows = []
    for j, (name, unit) in enumerate(zip(names, units)):
        scale = 1e3 if unit == "m" else math.degrees(1.0)  # mm and degrees at the I/O edge
        rows.append(
            {
                "name": name,
                "unit": "mm" if unit == "m" else "deg",
                "bias": raw.get(name, float("nan")) * scale,
                "true": float(true[j]) * scale,
                "estimate": float(est[j]) * scale,
                "std": float(std[j]) * scale,
                "z": float(z_joint[j]),
                "z_geometry_only": float(z_alone[j]),
            }
        )
    return rows


def run(args) -> dict:
    """The experiment (module docstring) with ``args``' samples, field, seed, hidden, passes and misfit_mm."""
    t_start = time.perf_counter()
    n_train = round(args.samples * 5874 / 7342)
    spec = EffectSpec.parse(f"field={args.field}")
    c = simulate(
        SimConfig(
            robot="ur5", trajectory=True, samples=args.samples, train_samples=n_train, seed=args.seed, effects=[spec]
        )
    )
    q = torch.cat([c.train.q, c.test.q])
    y = torch.cat([c.train.p, c.test.p])
    with torch.no_grad():
        clean = MeasurementModel(c.model.robot, [])(Context(q=c.q_true))  # the true robot, no field, no noise
        truth_y = c.model(Context(q=c.q_true))  # with the field

    start = load_robot("ur5")  # nominal geometry; tracker pose and lever arm by a rigid fit
    place_instrument_and_tool(start, c.train.q, c.train.p)
    cfg = AdaptiveConfig(passes=args.passes, sigma_misfit=args.misfit_mm * 1e-3)
    net = random_features(hidden=args.hidden, seed=args.seed + 1)
    joint = AdaptiveEKF(start, net, cfg)
    params = joint.identify(c.train.q)
    joint.parameters = params
    # exact fit (the same values from any poses that determine the parameters): every 5th training sample will do
    truth = joint.batch(c.q_true[:n_train:5], clean[:n_train:5], priors=False)
    t_filter = time.perf_counter()
    res = joint.run(q, y, n_train)
    t_filter = time.perf_counter() - t_filter
    alone = AdaptiveEKF(start, None, cfg, params).run(q, y, n_train)

    z_joint, z_alone = _z(res, truth), _z(alone, truth)
    d = res.gamma - truth.gamma
    nees = float(d @ torch.linalg.solve(res.gamma_covariance, d))
    raw = dict(zip(c.truth["geometry"]["names"], c.truth["geometry"]["delta"]))
    rows = _rows(res, truth, raw, z_joint, z_alone)
    te = slice(n_train, None)
    return {
        "parameters": len(rows),
        "within_3sigma": int((z_joint.abs() < 3).sum()),
        "max_abs_z": float(z_joint.abs().max()),
        "rms_z": float(z_joint.square().mean().sqrt()),
        "nees_gamma": nees,
        "nees_dof": len(d),
        "rmse_test_mm": rmse_mm(res.prediction[te] - truth_y[te]),
        "rmse_geometry_only_test_mm": rmse_mm(alone.prediction[te] - truth_y[te]),
        "rmse_test_meas_mm": rmse_mm(res.prediction[te] - y[te]),
        "rmse_geometry_only_test_meas_mm": rmse_mm(alone.prediction[te] - y[te]),
        "geometry_only_within_3sigma": int((z_alone.abs() < 3).sum()),
        "geometry_only_max_abs_z": float(z_alone.abs().max()),
        "std_ratio_median": float((res.gamma_std / alone.gamma_std).median()),  # what sharing with the network costs
        "nis_mean": float(res.nis.nanmean()),
        "status": res.status,
        "linearisation_remainder_m": [r["total_remainder_m"] for r in res.relinearisations],
        "field_rms_mm": c.truth["effects"][0]["rms_m"] * 1e3,
        "field_variation_mm": c.truth["effects"][0]["variation_m"] * 1e3,
        "samples": args.samples,
        "train": n_train,
        "seed": args.seed,
        "hidden": args.hidden,
        "passes": args.passes,
        "misfit_mm": args.misfit_mm,
        "filter_seconds": t_filter,
        "seconds": time.perf_counter() - t_start,
        "rows": rows,
    }


def table(result: dict) -> str:
    lines = [
        f"{'parameter':16s} {'unit':>4s} {'sim bias':>10s} {'true':>10s} {'estimate':>10s} {'std':>9s} "
        f"{'|err|/std':>9s} {'geo-only':>9s}"
    ]
    for r in result["rows"]:
        bias = "" if math.isnan(r["bias"]) else f"{r['bias']:+.5f}"
        lines.append(
            f"{r['name']:16s} {r['unit']:>4s} {bias:>10s} {r['true']:+.5f} {r['estimate']:+.5f} "
            f"{r['std']:9.5f} {abs(r['z']):9.2f} {abs(r['z_geometry_only']):9.1f}"
        )
    lines.append(
        f"within 3 sigma: {result['within_3sigma']} / {result['parameters']} (max |z| "
        f"{result['max_abs_z']:.2f}, rms z {result['rms_z']:.2f}; NEES of gamma {result['nees_gamma']:.1f} "
        f"for {result['nees_dof']} parameters); geometry alone: {result['geometry_only_within_3sigma']} / "
        f"{result['parameters']} (max |z| {result['geometry_only_max_abs_z']:.1f})"
    )
    lines.append(
        f"held-out RMSE vs truth: geometry + network {result['rmse_test_mm']:.4f} mm, geometry alone "
        f"{result['rmse_geometry_only_test_mm']:.4f} mm (vs measurements {result['rmse_test_meas_mm']:.4f} / "
        f"{result['rmse_geometry_only_test_meas_mm']:.4f} mm); field {result['field_rms_mm']:.3f} mm RMS, "
        f"{result['field_variation_mm']:.3f} mm variation"
    )
    lines.append(
        f"NIS mean {result['nis_mean']:.2f} (3 expected); linearisation remainder per pass "
        f"{', '.join(f'{v:.1e}' for v in result['linearisation_remainder_m'])} m; filter "
        f"{result['filter_seconds']:.1f} s, all {result['seconds']:.1f} s"
    )
    return "\n".join(lines)
