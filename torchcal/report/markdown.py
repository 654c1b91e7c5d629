"""report.md and its plots."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from torchcal.calibrate import CalibrationRun


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_errors_per_pose(run: CalibrationRun, path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 3.2))
    x = torch.arange(len(run.holdout_idx))
    for s, color in zip(run.stages, ("0.6", "tab:orange", "tab:blue", "tab:green")):
        ax.plot(x, s.holdout_errors * 1e3, ".", ms=3, color=color, label=f"{s.name} (RMSE {s.rmse * 1e3:.3f} mm)")
    ax.set_xlabel("held-out pose")
    ax.set_ylabel("|position error| [mm]")
    ax.legend(fontsize=8)
    ax.set_title("Held-out position error per pose")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_histograms(run: CalibrationRun, path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    first, last = run.stages[0], run.stages[-1]
    hi = float(max(first.holdout_errors.max(), last.holdout_errors.max())) * 1e3
    bins = torch.linspace(0, hi, 40).tolist()
    ax.hist((first.holdout_errors * 1e3).tolist(), bins=bins, alpha=0.6, color="0.5", label=f"before ({first.name})")
    ax.hist((last.holdout_errors * 1e3).tolist(), bins=bins, alpha=0.7, color="tab:blue", label=f"after ({last.name})")
    ax.set_xlabel("|position error| [mm], held-out poses")
    ax.set_ylabel("poses")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_error_vs_joints(run: CalibrationRun, path: Path) -> None:
    plt = _plt()
    dof = run.robot.dof
    cols = 3
    rows = math.ceil(dof / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(10, 2.6 * rows), squeeze=False)
    q = run.data.q[run.holdout_idx]
    first, last = run.stages[0], run.stages[-1]
    for j in range(rows * cols):
        ax = axes[j // cols][j % cols]
        if j >= dof:
            ax.axis("off")
            continue
        ax.plot(q[:, j].tolist(), (first.holdout_errors * 1e3).tolist(), ".", ms=2, color="0.6", label="before")
        ax.plot(q[:, j].tolist(), (last.holdout_errors * 1e3).tolist(), ".", ms=2, color="tab:blue", label="after")
        ax.set_xlabel(f"q{j + 1} [rad]")
        if j % cols == 0:
            ax.set_ylabel("|error| [mm]")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Held-out error against each joint")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(v: float, unit: str) -> str:
    if unit == "rad":
        return f"{math.degrees(v) * 3600:.2f}″"
    return f"{v * 1e3:.4f} mm"


def write_markdown(run: CalibrationRun, report: dict, out: Path) -> None:
    plot_errors_per_pose(run, out / "errors_per_pose.png")
    plot_histograms(run, out / "histogram.png")
    plot_error_vs_joints(run, out / "error_vs_joints.png")
    gt = report["global_test"]
    lines = [
        f"# Calibration of {report['robot']} ({report['method']})",
        "",
        f"{report['n_train']} poses fitted, {report['n_holdout']} held out ({report['split']['kind']} split, "
        f"seed {report['split']['seed']}). All errors below are on the held-out poses.",
        "",
        "| model | RMSE [mm] | max [mm] |",
        "|---|---:|---:|",
    ]
    for s in run.stages:
        lines.append(f"| {s.name} | {s.rmse * 1e3:.4f} | {float(s.holdout_errors.max()) * 1e3:.4f} |")
    lines += [
        "",
        "*nominal*: nominal geometry with the tracker pose and lever arm fitted; *geometric*: after the "
        "kinematic calibration (unchanged when the method fits no geometry); *learned*: with the correction network.",
        "",
        "## Global test",
        "",
        f"Variance factor {gt['statistic']:.3f} against the bound {gt['threshold']:.3f} (chi-square, "
        f"alpha {gt['alpha']}, redundancy {gt['redundancy']}): **{'passed' if gt['passed'] else 'failed'}**. "
        + ("The functional and stochastic models agree with the data." if gt["passed"] else
           "The residuals are larger than the stochastic model allows: the model lacks something, or the "
           "measurement precision is overstated."),
        "",
    ]
    if report["outliers"]["lines"]:
        lines += [f"Possible outliers (|w| > 3.29), file lines: {report['outliers']['lines'][:30]}", ""]
    par = report["parameters"]
    lines += ["## Parameters", "", "| parameter | correction | std |", "|---|---:|---:|"]
    for e in par["estimated"]:
        lines.append(f"| {e['name']} | {_fmt(e['correction'], e['unit'])} | {_fmt(e['std'], e['unit'])} |")
    if par["identifiability"] and par["identifiability"]["fixed"]:
        ida = par["identifiability"]
        lines += ["", "### Held fixed", "",
                  f"Identifiability: rank {ida['rank']} of {ida['n_candidates']} candidates (tolerance "
                  f"{ida['tol']:.0e}); dependent groups: "
                  + "; ".join("{" + ", ".join(g) + "}" for g in ida["dependent_groups"]), ""]
        for f in ida["fixed"]:
            lines.append(f"- `{f['name']}`: {f['reason']}")
    if par["largest_correlations"]:
        lines += ["", "### Largest correlations", ""]
        for c in par["largest_correlations"][:5]:
            lines.append(f"- {c['a']} / {c['b']}: {c['rho']:+.3f}")
    if report["effects"]:
        lines += ["", "## Effects", "", "| kind | joint | RMSE before [mm] | RMSE after [mm] |", "|---|---|---:|---:|"]
        for e in report["effects"]:
            lines.append(f"| {e['kind']} | {e['joint'] if e['joint'] is not None else '-'} | "
                         f"{e['rmse_before_mm']:.4f} | {e['rmse_after_mm']:.4f} |")
    lines += ["", "## Plots", "", "![errors per pose](errors_per_pose.png)", "", "![histogram](histogram.png)", "",
              "![error against joints](error_vs_joints.png)", ""]
    if report["notes"]:
        lines += ["## Notes", ""] + [f"- {n}" for n in report["notes"]] + [""]
    (out / "report.md").write_text("\n".join(lines), encoding="utf-8")
