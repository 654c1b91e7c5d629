"""Plots and the report.md section of an ``integrated`` run (the ANN-EKF, :mod:`torchcal.pipeline.integrated`).

The paper's Figs. 9 and 11 show, per sample, the deviations of the geometric part (devG), the non-geometric
part (devNG) and their sum (devAll) from the simulated truth, with the training (filtered) samples first and
the test (predicted) samples after them. Measured data have no truth, so the measurement is split at the
calibrated kinematic model instead (:meth:`IntegratedFilter.deviations`); devAll is then the filter's error
against the measurement, tracker noise included.
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchcal.report._figures import TITLE_Y, save, subplots


def _rms(a: torch.Tensor) -> float:
    return float(a.norm(dim=-1).square().mean().sqrt()) if len(a) else float("nan")


def plot_deviations(filt, path: Path) -> None:
    """devG, devNG, devAll per sample and axis [mm] (the paper's Figs. 9 and 11)."""
    dev = filt.deviations()
    n = filt.n_train
    fig, axes = subplots(3, 1, figsize=(9, 6.5), sharex=True)
    for ax, (name, a) in zip(axes, dev.items()):
        for j, c in enumerate("xyz"):
            ax.plot((a[:, j] * 1e3).tolist(), lw=0.6, label=c)
        ax.axvline(n, color="k", lw=0.8)
        ax.set_ylabel(f"{name} [mm]")
        ax.set_title(
            f"{name}: RMS {_rms(a[:n]) * 1e3:.4f} mm filtered, {_rms(a[n:]) * 1e3:.4f} mm predicted",
            fontsize=9,
            y=TITLE_Y,
        )
    axes[0].legend(ncol=3, fontsize=7, loc="upper left")
    axes[-1].set_xlabel(f"sample (the first {n} filtered, the held-out ones after the line predicted)")
    save(fig, path, margins={"left": 0.09, "right": 0.985, "bottom": 0.08, "top": 0.96, "hspace": 0.3})


def plot_correction(filt, path: Path) -> None:
    """The observed non-geometric part ``y - G`` against the filter's network output, per axis [mm] (Fig. 12)."""
    observed = filt.y - filt.kinematic
    fig, axes = subplots(3, 1, figsize=(9, 5.5), sharex=True)
    for j, (ax, c) in enumerate(zip(axes, "xyz")):
        ax.plot((observed[:, j] * 1e3).tolist(), lw=0.5, color="0.6", label="measured - kinematic model")
        ax.plot((filt.nongeometric[:, j] * 1e3).tolist(), lw=0.8, color="tab:blue", label="network (filter)")
        ax.axvline(filt.n_train, color="k", lw=0.8)
        ax.set_ylabel(f"{c} [mm]")
    axes[0].legend(fontsize=7, loc="upper left")
    axes[-1].set_xlabel("sample")
    save(fig, path, margins={"left": 0.09, "right": 0.985, "bottom": 0.09, "top": 0.98, "hspace": 0.12})


def _length(gate) -> str:
    """A gate length as the report writes it (an infinite or absent gate: none)."""
    return "none" if gate is None or gate == float("inf") else f"{gate:g}"


def ekf_section(run, out: Path) -> list[str]:
    """report.md lines about the filter pass, with its plots written into ``out``; none for other methods."""
    filt = getattr(run, "filter", None)
    if filt is None:
        return []
    plot_deviations(filt, out / "ekf_deviations.png")
    plot_correction(filt, out / "ekf_correction.png")
    res, n = filt.result, filt.n_train
    ev = next((e["evidence"] for e in run.effects_report if e.get("name") == "integrated"), {})
    lines = [
        "## Integrated ANN-EKF",
        "",
        f"The filter updated the network's weights on the {n} training samples (state: {res.w.shape[-1]} weights "
        f"and the probe position; status {res.status[0]}, {res.seconds:.1f} s, mean NIS "
        f"{float(res.nis[0, :n].mean()):.2f} against 3 for a consistent filter) and predicted the "
        f"{len(filt.y) - n} held-out samples without updates.",
        "",
    ]
    sel, ps = ev.get("selection"), ev.get("predictive_sigma")
    if sel and sel.get("chosen"):
        gate = next(
            (e["params"].get("support_gate_length") for e in run.effects_report if e.get("name") == "integrated"), None
        )
        gh = sel.get("gate_on_holdout")
        origin = (
            f" (validation chose {_length(gh['validation_gate_length'])}, the held-out samples "
            f"{_length(gh['holdout_gate_length'])}; the shorter is kept)"
            if gh
            else ""
        )
        lines += [
            f"Chosen on the last {sel['n_validation']} training samples: {sel['chosen']}, region gate length "
            f"{_length(gate)}{origin} (report.json: the candidates).",
            "",
        ]
    refit = ev.get("refit")
    if refit and refit.get("n_samples") and not refit.get("skipped"):
        lines += [
            f"The model written (model.pt, what predict uses) is this choice fitted again on all {refit['n_samples']} "
            "samples, training and held-out; the held-out errors of this report are those of the fit on the "
            "training samples, the only ones that did not see them.",
            "",
        ]
    if ps:
        hold = ps["coverage_2sigma_holdout"]
        lines += [
            f"Predicted standard deviation per sample (predict's sx, sy, sz): one scale factor "
            f"({ps['scale']:.3g}) calibrated on the validation block to {ps['target_coverage_2sigma'] * 100:.0f} % "
            f"within 2 sigma; within 2 sigma: validation {ps['coverage_2sigma_validation'] * 100:.1f} %, "
            f"held-out {'-' if hold is None else f'{hold * 100:.1f}'} %.",
            "",
        ]
    steps = ev.get("holdout_rmse_steps_mm", {})
    if steps:
        lines += ["| step | held-out RMSE [mm] |", "|---|---:|"]
        lines += [f"| {k.replace('_', ' ')} | {v:.4f} |" for k, v in steps.items()]
        lines += [
            f"| after the filter (final model) | {run.stages[-1].rmse * 1e3:.4f} |",
            f"| the filter's own test-phase prediction | {ev['holdout_rmse_filter_prediction_mm']:.4f} |",
            "",
        ]
    lines += [
        "Deviations per sample (as the paper's Figs. 9 and 11; without a truth, the measurement is split at the "
        "calibrated kinematic model G: devG = filter state - G, devNG = network - (measured - G), devAll = "
        "filter prediction - measured):",
        "",
        "![filter deviations](ekf_deviations.png)",
        "",
        "![non-geometric part](ekf_correction.png)",
        "",
    ]
    return lines
