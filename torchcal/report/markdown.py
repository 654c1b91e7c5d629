"""report.md and its plots."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from torchcal.diagnose.score import named_p
from torchcal.pipeline import CalibrationRun
from torchcal.pipeline.prior import moved_words
from torchcal.report._figures import TITLE_Y, save, subplots
from torchcal.report.ekf_plots import ekf_section


def plot_errors_per_pose(run: CalibrationRun, path: Path) -> None:
    """Each held-out pose's error after the kinematic calibration and with the final model, the poses sorted by the
    former: what each pose gained, and the poses the final model leaves above the rest. The steps between are the
    story table's (drawn here, their points lay over each other and hid both)."""
    first, last = _geometric(run), run.stages[-1]
    order = torch.argsort(first.holdout_errors.detach().cpu())
    x = torch.arange(len(order)).tolist()
    fig, ax = subplots(figsize=(9, 3.2))
    # from the kinematic calibration on: the nominal model's error (several times larger) would set the scale and
    # hide the steps that follow; its RMSE is in the title
    shown = [(first, "0.55", "kinematic calibration")]
    if last is not first:
        shown.append((last, "tab:blue", f"final ({last.name})"))
    for s, color, name in shown:
        e = (s.holdout_errors.detach().cpu()[order] * 1e3).tolist()
        ax.plot(x, e, ".", ms=3, color=color, label=f"{name}: RMSE {s.rmse * 1e3:.3f} mm")
    ax.set_xlabel("held-out pose, sorted by its error after the kinematic calibration")
    ax.set_ylabel("|position error| [mm]")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(
        f"Held-out position error per pose (nominal geometry: RMSE {run.stages[0].rmse * 1e3:.3f} mm)",
        fontsize=10,
        y=TITLE_Y,
    )
    save(fig, path, margins={"left": 0.08, "right": 0.985, "bottom": 0.15, "top": 0.9})


def plot_histograms(run: CalibrationRun, path: Path) -> None:
    fig, ax = subplots(figsize=(6, 3.2))
    first, last = _geometric(run), run.stages[-1]
    hi = float(max(first.holdout_errors.max(), last.holdout_errors.max())) * 1e3
    bins = torch.linspace(0, hi, 40).tolist()
    ax.hist((first.holdout_errors * 1e3).tolist(), bins=bins, alpha=0.6, color="0.5", label="kinematic calibration")
    if last is not first:
        e = (last.holdout_errors * 1e3).tolist()
        ax.hist(e, bins=bins, alpha=0.7, color="tab:blue", label=f"final ({last.name})")
    ax.set_xlabel("|position error| [mm], held-out poses")
    ax.set_ylabel("poses")
    ax.legend(fontsize=8)
    save(fig, path, margins={"left": 0.11, "right": 0.98, "bottom": 0.16, "top": 0.96})


def plot_error_vs_joints(run: CalibrationRun, path: Path) -> None:
    dof = run.robot.dof
    cols = 3
    rows = math.ceil(dof / cols)
    fig, axes = subplots(rows, cols, figsize=(10, 2.6 * rows), squeeze=False)
    q = run.data.q[run.holdout_idx]
    first, last = _geometric(run), run.stages[-1]
    for j in range(rows * cols):
        ax = axes[j // cols][j % cols]
        if j >= dof:
            ax.axis("off")
            continue
        ax.plot(q[:, j].tolist(), (first.holdout_errors * 1e3).tolist(), ".", ms=2, color="0.6", label="kinematic")
        if last is not first:
            ax.plot(q[:, j].tolist(), (last.holdout_errors * 1e3).tolist(), ".", ms=2, color="tab:blue", label="final")
        ax.set_xlabel(f"q{j + 1} [{'m' if run.robot.joint_types[j] == 'prismatic' else 'rad'}]")
        if j % cols == 0:
            ax.set_ylabel("|error| [mm]")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Held-out error against each joint")
    save(
        fig,
        path,
        margins={
            "left": 0.085,
            "right": 0.985,
            "bottom": 0.2 / rows,
            "top": 1 - 0.2 / rows,
            "hspace": 0.45,
            "wspace": 0.3,
        },
    )


def _geometric(run: CalibrationRun):
    """The kinematic calibration's stage: where the figures of the held-out error start (the nominal model's error,
    several times larger, would set their scale)."""
    return next(s for s in run.stages if s.name == "geometric")


def plot_error_map(run: CalibrationRun, path: Path) -> None:
    """Held-out probe positions seen from above and from the side, coloured by the error before and after."""
    hold = run.data.subset(run.holdout_idx)
    with torch.no_grad():
        p = run.model.robot.probe_in_base(hold.q)
    geo = next(s for s in run.stages if s.name == "geometric")
    shown = [geo, run.stages[-1]] if run.stages[-1] is not geo else [geo]
    vmax = float(max(s.holdout_errors.max() for s in shown)) * 1e3
    # fixed margins, the colour bar taking its room from the axes: the constrained layout measured every label's
    # extent at each draw, half of this figure's time
    fig, axes = subplots(2, len(shown), figsize=(5.6 * len(shown), 8), squeeze=False)
    fig.subplots_adjust(left=0.1 if len(shown) == 1 else 0.06, right=0.97, bottom=0.07, top=0.96, hspace=0.25)
    radius = p[:, :2].norm(dim=-1)
    for k, s in enumerate(shown):
        e = (s.holdout_errors * 1e3).tolist()
        sc = axes[0][k].scatter(p[:, 0].tolist(), p[:, 1].tolist(), c=e, s=9, cmap="viridis", vmin=0, vmax=vmax)
        axes[0][k].set_xlabel("x [m] (robot base)")
        axes[0][k].set_ylabel("y [m]")
        name = s.name if k == 0 or s.name == "geometric" else f"final ({s.name})"
        axes[0][k].set_title(f"{name}: RMSE {s.rmse * 1e3:.4f} mm", fontsize=10, y=TITLE_Y)
        axes[1][k].scatter(radius.tolist(), p[:, 2].tolist(), c=e, s=9, cmap="viridis", vmin=0, vmax=vmax)
        axes[1][k].set_xlabel("distance from the base axis [m]")
        axes[1][k].set_ylabel("z [m]")
    fig.colorbar(sc, ax=axes, label="|position error| [mm], held-out poses", shrink=0.6)
    save(fig, path, 100, tight=False)


def plot_decision(run: CalibrationRun, decision, path: Path, figure: DecisionFigure | None = None) -> None:
    """Residual along the effect's direction against its regressor, before and after (one decision); drawn in
    ``figure`` where a report draws several (:class:`DecisionFigure`)."""
    from torchcal.diagnose.views import residual_view
    from torchcal.effects import Context

    train = run.data.subset(run.train_idx)
    ctx = Context.from_measurements(train, trajectory=run.trajectory)
    before, after = decision.models
    v = residual_view(decision.candidate, before, after, ctx, train.p)
    (figure or DecisionFigure()).draw(v, decision, path)


class DecisionFigure:
    """The figure of :func:`plot_decision`, built once and drawn for each of a run's decisions: its axes, legends,
    titles and ticks are the same in every one, and building them was half of each figure's time; each decision
    sets its points, its variable's label, the limits and the suptitle, and what it drew is undone before the next
    (the images are those of a figure built for it alone)."""

    #: the panels: the residual drawn, its colour, the title
    PANELS = (
        ("before", "0.45", "before: residual of the model without it"),
        ("after", "tab:blue", "after: residual with it, the geometry refitted jointly"),
    )

    def __init__(self) -> None:
        fig, axes = subplots(1, 2, figsize=(10, 4.0), sharey=True)
        self.fig, self.axes, self.lines, self.notes = fig, axes, [], []
        for ax, (_, color, title) in zip(axes, self.PANELS):
            (res,) = ax.plot([], [], ".", ms=2.5, color=color, label="residual along the effect's direction")
            (eff,) = ax.plot([], [], ".", ms=2, color="tab:red", label="fitted effect, less its mean")
            self.lines.append((res, eff))
            ax.axhline(0.0, color="k", lw=0.5)
            ax.set_title(title, fontsize=9, y=TITLE_Y)
            ax.legend(fontsize=7, loc="upper left")
            self.notes.append(
                ax.text(0.99, 0.02, "", transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="tab:red")
            )
        axes[0].set_ylabel("[um]")
        self.title = fig.suptitle("", fontsize=9)
        fig.subplots_adjust(left=0.1, right=0.985, bottom=0.13, top=0.8, wspace=0.05)

    def draw(self, v: dict, decision, path: Path) -> None:
        """Draw one decision's view ``v`` (:func:`~torchcal.diagnose.views.residual_view`) into ``path``."""
        x = v["x"].tolist()
        # less its mean over the poses: a constant along the effect's direction is a joint offset or an instrument
        # shift the geometry carries (a compliance under torques of one sign sat 1 mm below residuals about zero)
        effect = v["effect"] - v["effect"].mean()
        order = torch.argsort(v["x"]).tolist()
        xs, ys = [x[i] for i in order], (effect[order] * 1e6).tolist()
        for ax, (res, eff), (key, _, _) in zip(self.axes, self.lines, self.PANELS):
            res.set_data(x, (v[key] * 1e6).tolist())
            eff.set_data(xs, ys)
            ax.set_xlabel(v["xlabel"])
            ax.relim()
            ax.set_autoscale_on(True)
        for ax in self.axes:
            ax.autoscale_view()
        # an effect far beyond the residuals (a candidate confounded with the geometry, which takes the rest: a
        # rejected cyclic term on Series C reached 16 mm over residuals of 1 mm) would set the scale and hide them
        lim = 1.15e6 * float(torch.cat([v["before"], v["after"]]).abs().max())
        reach = 1e6 * float(effect.abs().max())
        beyond = reach > 1.5 * lim
        if beyond:
            self.axes[0].set_ylim(-lim, lim)
        for note in self.notes:
            note.set_text(f"fitted effect beyond the axis: up to {reach:.3g} um" if beyond else "")
            note.set_visible(beyond)
        verdict = "accepted" if decision.accepted else "rejected"
        self.title.set_text(
            f"{decision.candidate.name}: {verdict} (training poses). The geometry was refitted with the effect and "
            "carries its mean: the fitted effect can exceed\nthe trend the geometry alone left, whose share of it the "
            "geometry had absorbed"
        )
        save(self.fig, path, 100, tight=False)  # margins set once; not pyplot's, so it stays for the next decision


def _fmt(v: float, unit: str) -> str:
    """A parameter's value as the report prints it: an angle in arc seconds, a length in mm, a ratio (unit 1, a
    readings map's) as the bare number."""
    if unit == "rad":
        return f"{math.degrees(v) * 3600:.2f}″"
    if unit == "m":
        return f"{v * 1e3:.4f} mm"
    return f"{v:.6g}"


STAGE_TEXT = {
    "nominal": "nominal geometry; tracker pose and lever arm fitted",
    "geometric": "kinematic calibration: identifiable geometric errors, tracker pose, lever arm",
    "learned": "learned residual model (kernel regression or correction network)",
    "integrated": "integrated ANN-EKF: geometry and network estimated along the trajectory",
}


def _g(v, fmt=".3g") -> str:
    return "-" if v is None else format(v, fmt)


def _stations_section(report: dict) -> list[str]:
    """A table of the instrument stations (tracker position in the base frame, its sigma, held-out RMSE, rows) and
    one of the probes (lever arm and sigma), for a run of several."""
    lines: list[str] = []

    def um(v):
        return "-" if v is None else f"{v * 1e6:.1f}"

    if report.get("stations"):
        lines += [
            "## Instrument stations",
            "",
            "One instrument pose per station, the robot's calibration shared. Tracker origin in the robot base frame "
            "[m]; sigma of the pose's translation [um] and rotation [urad]; held-out RMSE of the station's rows.",
            "",
            "| station | tracker in base x, y, z [m] | sigma t [um] | sigma r [urad] | held-out RMSE [mm] | rows "
            "train / held out |",
            "|---|---|---|---|---:|---|",
        ]
        for name, st in report["stations"].items():
            T = torch.tensor(st["T_tracker_base"], dtype=torch.float64)
            pos = (-T[:3, :3].T @ T[:3, 3]).tolist()
            sd = st["std"]
            rm = "-" if st["rmse_holdout_mm"] is None else f"{st['rmse_holdout_mm']:.4f}"
            sig_t = ", ".join(um(sd[c]) for c in ("tx", "ty", "tz"))
            sig_r = ", ".join(um(sd[c]) for c in ("rx", "ry", "rz"))
            lines.append(
                f"| {name} | {pos[0]:.4f}, {pos[1]:.4f}, {pos[2]:.4f} | {sig_t} | {sig_r} "
                f"| {rm} | {st['n_train']} / {st['n_holdout']} |"
            )
        lines.append("")
    if report.get("probes"):
        lines += [
            "## Probes",
            "",
            "One lever arm per probe (flange frame).",
            "",
            "| probe | x, y, z [mm] | sigma x, y, z [um] |",
            "|---|---|---|",
        ]
        for name, pr in report["probes"].items():
            t = pr["t_flange_probe_m"]
            lines.append(
                f"| {name} | {t[0] * 1e3:.4f}, {t[1] * 1e3:.4f}, {t[2] * 1e3:.4f} | "
                f"{', '.join(um(pr['std_m'][c]) for c in ('x', 'y', 'z'))} |"
            )
        lines.append("")
    return lines


def write_markdown(run: CalibrationRun, report: dict, out: Path) -> None:
    plot_errors_per_pose(run, out / "errors_per_pose.png")
    plot_histograms(run, out / "histogram.png")
    plot_error_vs_joints(run, out / "error_vs_joints.png")
    plot_error_map(run, out / "error_map.png")
    lines = _story_section(run, report)
    lines += _prior_section(report)
    lines += _orientation_section(report)
    lines += _stations_section(report)
    lines += _diagnosis_section(run, report, out)
    lines += _region_section(run, report, out)
    note = (report.get("trust") or {}).get("note")
    lines += ["", f"Predictive sigma (sx, sy, sz of predict and compensate) {note}.", ""] if note else []
    lines += _unexplained_section(report, out)
    lines += ekf_section(run, out)
    lines += _global_test_section(report)
    lines += _outliers_section(report)
    lines += _parameters_section(report["parameters"])
    lines += _effects_section(report["effects"])
    lines += [
        "",
        "## Plots",
        "",
        "Each held-out pose's error after the kinematic calibration (grey) and with the final model (blue), the "
        "poses sorted by the former (the nominal model's RMSE, several times larger, is in the title; the steps "
        "between are in the story's table): look for poses the final model leaves far above the rest, or above "
        "their kinematic error.",
        "",
        "![errors per pose](errors_per_pose.png)",
        "",
        "The held-out errors of the kinematic calibration and of the final model: the final one sits to the left, "
        "with a shorter tail, where the effects helped.",
        "",
        "![histogram](histogram.png)",
        "",
        "The held-out error against each joint, kinematic calibration and final model: a trend or a band along a "
        "joint that the final model still shows is structure in that joint.",
        "",
        "![error against joints](error_vs_joints.png)",
        "",
    ]
    if report["notes"]:
        lines += ["## Notes", ""] + [f"- {n}" for n in report["notes"]] + [""]
    (out / "report.md").write_text("\n".join(lines), encoding="utf-8")


def _story_section(run: CalibrationRun, report: dict) -> list[str]:
    """The title and what each stage of the run brought on the held-out poses."""
    lines = [
        f"# Calibration of {report['robot']} ({report['method']})",
        "",
        f"{report['n_train']} poses fitted, {report['n_holdout']} held out ({report['split']['kind']} split, "
        f"seed {report['split']['seed']}). All errors below are on the held-out poses.",
        "",
        "## The story",
        "",
        "| step | model | RMSE [mm] | max [mm] |",
        "|---:|---|---:|---:|",
    ]
    for k, s in enumerate(run.stages):
        what = STAGE_TEXT.get(s.name, f"+ {s.name}, refitted jointly with the geometry")
        lines.append(f"| {k} | {s.name}: {what} | {s.rmse * 1e3:.4f} | {float(s.holdout_errors.max()) * 1e3:.4f} |")
    return lines + [
        "",
        f"Before: {report['rmse_before_mm']:.4f} mm; after the geometric fit: {report['rmse_geometric_mm']:.4f} mm; "
        f"final: {report['rmse_after_mm']:.4f} mm.",
        "",
        "The held-out probe positions from above (top) and from the side (bottom), coloured by their error after the "
        "kinematic calibration (left) and with the final model (right), on one colour scale: look for regions "
        "where the error stays high.",
        "",
        *_narrow_lines(report),
        "![error map](error_map.png)",
        "",
    ]


def _narrow_lines(report: dict) -> list[str]:
    """The story's word on joints the training poses hardly moved: what a prediction beyond them rests on."""
    narrow = (report.get("region") or {}).get("narrow_joints") or []
    if not narrow:
        return []
    from torchcal.pipeline.checks import NarrowJoint, narrow_note

    note = narrow_note([NarrowJoint(**n) for n in narrow])
    return [f"**{note[0].upper()}{note[1:]}.**", ""]


def _global_test_section(report: dict) -> list[str]:
    gt = report["global_test"]
    return [
        "## Global test",
        "",
        f"Variance factor {gt['statistic']:.3f} against the bound {gt['threshold']:.3f} (chi-square, "
        f"alpha {gt['alpha']}, redundancy {gt['redundancy']}): **{'passed' if gt['passed'] else 'failed'}**. "
        + ("The functional and stochastic models agree with the data." if gt["passed"] else global_test_finding(gt)),
        "",
    ]


def global_test_finding(gt: dict) -> str:
    """What a failed global test found, in words (report.json ``global_test``; :mod:`torchcal.diagnose.noise`): what
    the model leaves against the instrument's noise, and whether it reads as structure an effect may explain or as a
    unit or robot-description mistake. report.md and calibrate's warning say the same."""
    from torchcal.diagnose.noise import MISTAKE_SHARE, NoiseLevel

    noise = NoiseLevel(gt["noise"]["sigma_m"], gt["noise"]["source"], gt["noise"]["dof"])
    times = "" if gt["times_noise"] is None else f", {gt['times_noise']:.3g} times the noise level"
    left = f"The final model leaves {gt['unexplained_mm']:.4f} mm (held-out RMSE){times} ({noise.words()}). "
    if gt["reading"] == "mistake":
        return left + (
            f"The kinematic calibration alone leaves {gt['geometric_share_of_reach']:.2g} of the arm's reach "
            f"({gt['reach_m']:.3g} m), more than {MISTAKE_SHARE:g}: this looks like a unit or robot-description "
            "mistake (a joint column in degrees or another unit? a robot description with a wrong length or angle? "
            "orientation columns that are not the probe's? --tracker-noise far too small?)."
        )
    return left + (
        "The model lacks structure the data show: see the effects and the unexplained structure above; "
        "predict's sigma includes what it leaves."
    )


def _outliers_section(report: dict) -> list[str]:
    """The gross errors left out of the training and held-out rows, by file line (the first 30 of each)."""
    lines = []
    for part, what in (("training", "training"), ("holdout", "held-out")):
        rows = (report["outliers"].get(part) or {}).get("rows") or []
        if rows:
            lines += [
                f"Gross errors left out of the {what} rows ({len(rows)}; file line: size): "
                + ", ".join(f"{r['line']}: {r['size_mm']:.3g} mm" for r in rows[:30])
                + (" ..." if len(rows) > 30 else "")
                + ("; " + rows[0]["hint"] if rows[0].get("hint") else ""),
                "",
            ]
    return lines


def _parameters_section(par: dict) -> list[str]:
    """The corrections and their std, then the parameters held fixed, the weak ones and the largest correlations."""
    lines = ["## Parameters", "", "| parameter | correction | std |", "|---|---:|---:|"]
    for e in par["estimated"]:
        lines.append(f"| {e['name']} | {_fmt(e['correction'], e['unit'])} | {_fmt(e['std'], e['unit'])} |")
    if par["identifiability"] and par["identifiability"]["fixed"]:
        ida = par["identifiability"]
        lines += [
            "",
            "### Held fixed",
            "",
            f"Identifiability: rank {ida['rank']} of {ida['n_candidates']} candidates (tolerance "
            f"{ida['tol']:.0e}); dependent groups: "
            + "; ".join("{" + ", ".join(g) + "}" for g in ida["dependent_groups"]),
            "",
        ]
        for f in ida["fixed"]:
            lines.append(f"- `{f['name']}`: {f['reason']}")
    if par["identifiability"] and par["identifiability"].get("weak"):
        lines += ["", "### Weakly determined", ""]
        lines += [f"- `{w['name']}`: {w['reason']}" for w in par["identifiability"]["weak"]]
    if par["largest_correlations"]:
        lines += ["", "### Largest correlations", ""]
        for c in par["largest_correlations"][:5]:
            lines.append(f"- {c['a']} / {c['b']}: {c['rho']:+.3f}")
    return lines


def effect_line(e: dict) -> str:
    """One found effect (an entry of the run's ``effects_report``) as the demo and ``calibrate`` print it: its name,
    its parameters with their units and the one p-value it was admitted on (named: the localisation's or the score
    test's, the same as report.md's)."""
    name = e["kind"] + (f" (joint {e['joint']})" if e["joint"] is not None else "")
    words = effect_params_words(e["params"])
    ev = e["evidence"]
    return name + (f": {words}" if words else "") + (f"; {named_p(ev)}" if "p_bonferroni" in ev else "")


def effect_params_words(params: dict) -> str:
    """An effect's fitted parameters as report.md and the terminal print them: ``k = 2.49e-06 rad/(N m) ± 9.1e-08``
    (the unit report.json gives beside the value; none for a parameter without one)."""
    return ", ".join(
        f"{k} = {v['value']:.3g}{' ' + v['unit'] if v.get('unit') else ''} ± {_g(v.get('std'), '.2g')}"
        for k, v in params.items()
        if isinstance(v, dict) and "value" in v
    )


def _effects_section(effects: list) -> list[str]:
    """The non-geometric effects fitted: their parameters and what each took off the held-out RMSE."""
    if not effects:
        return []
    lines = [
        "",
        "## Effects",
        "",
        "| kind | joint | parameters (value ± std) | RMSE before [mm] | RMSE after [mm] |",
        "|---|---|---|---:|---:|",
    ]
    for e in effects:
        params = effect_params_words(e["params"])
        kind = f"{e['kind']} (the prior run's, held; its RMSE)" if e.get("carried_from_prior") else e["kind"]
        lines.append(
            f"| {kind} | {e['joint'] if e['joint'] is not None else '-'} | {params or '-'} | "
            f"{e['rmse_before_mm']:.4f} | {e['rmse_after_mm']:.4f} |"
        )
    return lines


def _prior_section(report: dict) -> list[str]:
    """A calibration from a prior run: what the new poses moved, and every parameter's change in its prior sigmas."""
    pr = report.get("prior")
    if pr is None:
        return []
    moved = moved_words(pr["moved"], pr.get("moved_or_held_alike") or {}) or "nothing"
    if (pr.get("detectability") or {}).get("cannot_tell"):
        moved += " of what these rows can tell (below: what they cannot)"
    lines = [
        "## What moved since the prior run",
        "",
        f"Started from {pr['source']} (its model: the 'nominal' stage above). Moved beyond "
        f"{pr['moved_threshold_sigma']:g} prior sigma: **{moved}**"
        + (f" (released from their prior: {', '.join(pr['released'])})" if pr["released"] else "")
        + ". Prior sigma: the run's own, x"
        f"{pr['inflation']:g}, at least {pr['floor']['m'] * 1e6:g} um or urad; its s0 {pr['s0']:.3g}.",
        "",
        "| parameter | prior run | change | prior sigma | change / sigma |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in sorted(pr["parameters"], key=lambda r: -r["ratio"]):
        lines.append(
            f"| {r['name']} | {_fmt(r['prior'], r['unit'])} | {_fmt(r['change'], r['unit'])} | "
            f"{_fmt(r['sigma'], r['unit'])} | {r['ratio']:.2f} |"
        )
    return [*lines, "", *_untold_lines(pr.get("detectability"))]


def _untold_lines(d: dict | None) -> list[str]:
    """What the rows of a calibration from a prior could not have seen move (report.json ``prior.detectability``)."""
    if not d or not d["cannot_tell"]:
        return []
    more = d["poses_to_add"]
    lines = [
        "### What these rows cannot tell",
        "",
        f"A move of {d['move_sigma']:g} prior sigma of these parameters would not pass the "
        f"{d['threshold_sigma']:g}-sigma test here: the {d['rows']} rows give it only the share below and spread the "
        "rest over the parameters named; "
        "they may have moved unseen, so 'nothing moved' does not hold for them. "
        + (
            f"About {more} more poses like these would tell them all; `torchcal plan --run THIS_RUN --n {more}` "
            "chooses where, then update again with them."
            if more
            else "More poses that move them apart would (`torchcal plan --run THIS_RUN` chooses where)."
        ),
        "",
        "| parameter | change / sigma | share seen | seen from [sigma] | would go to |",
        "|---|---:|---:|---:|---|",
    ]
    for u in d["cannot_tell"]:
        seen = f"{u['detectable_from']:.1f}" if u["detectable_from"] is not None else "never"
        change = f"{u['change_sigma']:.2f}" if u.get("change_sigma") is not None else "-"
        name = u["name"] + (" (held: the prior run could not determine it)" if u.get("held") else "")
        lines.append(f"| {name} | {change} | {u['share']:.2f} | {seen} | {', '.join(u['absorbed_by']) or '-'} |")
    return [*lines, ""]


def _orientation_section(report: dict) -> list[str]:
    """The held-out orientation errors of a 6-D probe, stage by stage (only where the data carry orientation)."""
    o = report.get("orientation")
    if o is None:
        return []
    sigma = o["sigma_rad"]
    sigma = sigma if isinstance(sigma, str) else f"{math.degrees(sigma):.3g} deg per axis"
    lines = [
        "## Orientation",
        "",
        f"The probe measured its orientation too (a 6-D probe, {o['rows_fitted']} rows fitted; standard deviation "
        f"{sigma}). Each row's orientation residual is weighted by its own covariance, so no factor turns metres into "
        f"radians. Used in {o['fitted_in']}. The positions above are the same rows' positions.",
        "",
        "| step | RMS [deg] | max [deg] |",
        "|---|---:|---:|",
    ]
    lines += [f"| {s['name']} | {s['rms_holdout_deg']:.4f} | {s['max_holdout_deg']:.4f} |" for s in o["stages"]]
    only = o["estimable_only_with_orientation"]
    lines += [
        "",
        "Estimable only with the orientation rows (fixed by the same analysis of the positions alone): "
        + (", ".join(only) if only else "none")
        + "; the probe frame's rotation in the flange (tool.rx, tool.ry, tool.rz) is fitted from them.",
        "",
    ]
    return lines


def plot_joint_function(run: CalibrationRun, effect, path: Path) -> None:
    """An open joint-angle form over its joint's whole range: the function as fitted (dashed), as applied (faded
    beyond the fitted range, solid), the fitted range shaded and the physical bound marked."""
    from torchcal.effects.joint import joint_range

    lo, hi = joint_range(run.robot, effect.joint)
    dev = run.robot.device
    grid = torch.linspace(lo, hi, 801, dtype=torch.float64, device=dev)
    dof = run.robot.dof
    q = torch.zeros(len(grid), dof, dtype=torch.float64, device=dev)
    q[:, effect.j] = grid
    with torch.no_grad():
        raw = (effect.function(grid) * 1e3).cpu()
        applied = (effect._terms(q, fade=True).sum(-1) * 1e3).cpu()
    grid = grid.cpu()
    fig, ax = subplots(figsize=(7, 3))
    if effect.region is not None:
        a, b = (float(v) for v in effect.region)
        ax.axvspan(a, b, color="tab:green", alpha=0.12, label="fitted range")
    ax.plot(grid.tolist(), raw.tolist(), "--", color="0.5", lw=1, label="as fitted, continued")
    ax.plot(grid.tolist(), applied.tolist(), color="tab:blue", lw=1.5, label="as applied (fades beyond)")
    bound = run.options.loop.max_joint_error
    if bound is not None:
        for y in (bound * 1e3, -bound * 1e3):
            ax.axhline(y, color="tab:red", lw=0.8, ls=":")
    span = float(applied.abs().max())
    ax.set_ylim(-3 * max(span, 1e-6), 3 * max(span, 1e-6))
    ax.set_xlabel(f"q{effect.joint} [rad]")
    ax.set_ylabel("joint error [mrad]")
    ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{effect.kind}:{effect.joint} over the joint's range", y=TITLE_Y)
    save(fig, path)


def _region_section(run: CalibrationRun, report: dict, out: Path) -> list[str]:
    """Where the model holds: the calibrated region, what fades beyond it, each open form over its joint's range."""
    from torchcal.effects.joint import FADE_LENGTH, RegionForm

    reg = report.get("region")
    if not reg:
        return []
    lines = [
        "## Where the model holds",
        "",
        "The calibrated region: the range each joint covered in the poses fitted. Beyond it the open joint forms "
        + ("and the learned corrections " if reg["learned_fade"] else "")
        + f"fade to the geometry (Gaussian, length {FADE_LENGTH} rad); `predict` and `compensate` give every row's "
        "distance beyond it (`extrapolation`).",
        "",
        "| joint | from | to |",
        "|---|---:|---:|",
    ]
    for j, (a, b) in enumerate(zip(reg["joint_min"], reg["joint_max"]), start=1):
        lines.append(f"| q{j} | {a:.4g} | {b:.4g} |")
    lines += ["", *_beyond_lines((report.get("trust") or {}).get("beyond"))]
    for k, e in enumerate(run.model.effects):
        if isinstance(e, RegionForm):
            name = f"joint_function_{k}_{e.kind}_{e.joint}.png"
            plot_joint_function(run, e, out / name)
            lines += [f"![{e.kind}:{e.joint} over its joint's range]({name})", ""]
    return lines


#: the words for each model that may predict the rows beyond the region (torchcal.pipeline.beyond)
_BEYOND_WORDS = {
    "full": "the run's model",
    "geometric": "its kinematic calibration",
    "physical": "its geometry and physical effects",
    "nominal": "the nominal geometry with the fitted instrument pose and lever arm",
}


def _beyond_lines(beyond: dict | None) -> list[str]:
    """Which model predicts the rows beyond the region, on what evidence (report.json's ``trust.beyond``)."""
    if not beyond:
        return []
    if beyond.get("model") is None:
        return [f"Beyond the region: no model chosen ({beyond.get('rule')}).", ""]
    rmse = ", ".join(f"{k} {v:.4f} mm" for k, v in beyond["rmse_mm"].items())
    return [
        f"Beyond the region {_BEYOND_WORDS.get(beyond['model'], beyond['model'])} (`model` = {beyond['model']}) "
        f"predicts every row: the smallest error on {beyond['n_evidence']} {beyond['evidence']} ({rmse}).",
        "",
    ]


def _diagnosis_section(run: CalibrationRun, report: dict, out: Path) -> list[str]:
    diag = run.diagnosis
    if diag is None:
        return []
    # one figure for every decision's plot (DecisionFigure), built at the first
    figure = _Lazy(DecisionFigure)
    lines = [
        "## Closing the loop",
        "",
        f"Candidates ({len(diag.candidates)}): {', '.join(c.name for c in diag.candidates) or 'none'}. "
        f"Each round scores every remaining candidate at the current fit (score test, chi-square, Bonferroni "
        f"over the candidates at alpha {diag.alpha}); the significant ones, strongest first, are refitted "
        f"jointly with the geometry on {diag.n_fit} training poses and must lower the error on the other "
        f"{diag.n_validation} (validation poses; paired one-sided test at {diag.alpha_validation}).",
        "",
    ]
    if diag.skipped:
        lines += ["Left out: " + "; ".join(f"{s['name']} ({s['reason']})" for s in diag.skipped), ""]
    for r in diag.rounds:
        lines += _round_lines(run, r, out, figure)
    lines += [f"Stopped: {diag.stop}.", ""]
    return lines + _learned_lines(report)


class _Lazy:
    """``make()``, made at the first call and the same one after."""

    def __init__(self, make) -> None:
        self.make, self.made = make, None

    def __call__(self):
        if self.made is None:
            self.made = self.make()
        return self.made


def _round_lines(run: CalibrationRun, r: dict, out: Path, figure: _Lazy) -> list[str]:
    """One round of the closed loop: its fit, the score tests, the localisation, each decision (with its figure)."""
    diag = run.diagnosis
    lines: list[str] = []
    gt = r["global_test"]
    lines += [
        f"### Round {r['round']}",
        "",
        f"Current fit: variance factor {gt['statistic']:.3f} (bound {gt['threshold']:.3f}).",
        "",
        "Score test of each named candidate at the current fit (the strongest six):",
        "",
        "| candidate | k | chi2 | score test: log10 p | score test: Bonferroni p | BIC change | identifiable |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for s in r["scores"][:6]:
        lines.append(
            f"| {s.candidate.name} | {s.k} | {s.statistic:.1f} | {s.log10_p:.1f} | {s.p_bonferroni:.2g} | "
            f"{s.bic_change:.1f} | {'yes' if s.identifiable else 'no'} |"
        )
    lines.append("")
    if r.get("localisation"):
        lines += [
            "Localisation of the residual (penalised smooth per variable, Bonferroni over the variables): "
            + ", ".join(
                f"{loc['variable']} (share {loc['share']:.1%}, Bonferroni p = {loc['p_bonferroni']:.2g})"
                for loc in r["localisation"][:3]
            )
            + ". Open candidates: "
            + (", ".join(f"{c['name']} ({c['form']}, order {c['order']})" for c in r["open_candidates"]) or "none")
            + ".",
            "",
        ]
    for k, d in enumerate(diag.decisions):
        if d.round != r["round"]:
            continue
        v = d.validation
        verdict = "**accepted**" if d.accepted else "**rejected**"
        # a candidate rejected on its form (terms that cancel) is not put to the paired test: no z, no p to print
        tested = math.isfinite(v["z"]) and math.isfinite(v["p_value"])
        paired = (
            f"paired z = {v['z']:.2f}, p = {v['p_value']:.2g}" if tested else "no paired test: rejected on its form"
        )
        lines += [
            f"{d.candidate.name} ({named_p(d.score.to_dict())}): {verdict}: {d.reason}. Validation RMSE "
            f"{v['rmse_before_mm']:.4f} -> {v['rmse_after_mm']:.4f} mm ({paired}).",
            "",
        ]
        if d.models is not None:
            name = f"decision_{k + 1}_{d.candidate.name.replace(':', '_')}.png"
            plot_decision(run, d, out / name, figure())
            lines += [
                f"![{d.candidate.name}]({name})",
                "",
                "The training residual along the effect's direction against its variable, without the effect "
                "(left) and after the geometry was refitted jointly with it (right), with the fitted effect less its "
                "mean (a constant the geometry carries) in red (it can exceed the trend on the left: the geometry "
                "alone had absorbed a share of it): an effect the data demand leaves the right panel flat.",
                "",
            ]
    return lines


def _learned_lines(report: dict) -> list[str]:
    """The learned residual model's verdict, from report.json's effects (or rejections)."""
    lines: list[str] = []
    learned = [e for e in report["effects"] if e["kind"] == "learned"]
    rejected = [e for e in report.get("rejected", []) if e["kind"] == "learned"]
    if learned or rejected:
        entry = (learned or rejected)[0]
        # a learned model the held-out guard dropped carries the stage's evidence under ``admitted_by``
        ev = entry["evidence"].get("admitted_by", entry["evidence"])
        verdict = "accepted" if learned else "rejected"
        if "chosen" in ev:
            lines.append(
                f"Learned residual model: {ev['chosen']} {verdict} "
                f"(validation {ev['validation_rmse_before_mm']:.4f} -> {ev['validation_rmse_after_mm']:.4f} mm, "
                f"p = {ev['p_value']:.2g}; rule: {ev['rule']})"
                + (f"; then dropped: {entry['reason']}." if not learned and entry.get("reason") else ".")
            )
        else:
            lines.append(
                f"Learned residual model {verdict}" + (f": {entry['reason']}." if entry.get("reason") else ".")
            )
        lines.append("")
    return lines


def plot_unexplained(entry: dict, path: Path) -> None:
    """The smooth of the residual in one unexplained variable, with a 2-sigma band (``report.json`` entry)."""
    sm = entry["smooth"]
    x = torch.tensor(sm["grid"], dtype=torch.float64)
    f = torch.tensor(sm["value"], dtype=torch.float64)
    se = torch.tensor(sm["se"], dtype=torch.float64)
    joint = sm["unit"] == "rad"
    scale, unit = (1e6, "urad") if joint else (1e6, "um")
    fig, ax = subplots(figsize=(7, 3.6))
    se_shape = torch.tensor(sm["se_shape"], dtype=torch.float64) if "se_shape" in sm else None
    cols = [f, se, se_shape]
    if f.dim() == 1:
        cols = [None if c is None else c[:, None] for c in cols]
    names = ["joint error"] if joint else ["x", "y", "z"]
    for c, name in enumerate(names):
        v, s = cols[0][:, c] * scale, cols[1][:, c] * scale
        style = "o-" if len(x) <= 2 else "-"
        # where the band is wider than the curve's whole variation, the smooth's level is not determined (a constant
        # the geometry carries, a joint offset): its shape is drawn about zero, with the shape's own band (that of
        # the smooth less its mean), and without a band where the report has none for it
        shape_only = float(s.min()) > float(v.max() - v.min())
        if shape_only:
            v = v - v.mean()
            s = None if cols[2] is None else cols[2][:, c] * scale
        ax.plot(
            x.tolist(), v.tolist(), style, lw=1.2, label=name + (" (shape; level not determined)" if shape_only else "")
        )
        if s is not None:
            ax.fill_between(x.tolist(), (v - 2 * s).tolist(), (v + 2 * s).tolist(), alpha=0.2)
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel(entry["label"])
    ax.set_ylabel(f"residual smooth [{unit}]" + (" (tracker frame)" if not joint else ""))
    ax.set_title(
        f"unexplained: {entry['variable']} (share {entry['share']:.1%} of the residual, "
        f"Bonferroni p = {entry['p_bonferroni']:.2g})",
        fontsize=10,
        y=TITLE_Y,
    )
    ax.legend(fontsize=7)
    save(fig, path, 100, margins={"left": 0.135, "right": 0.98, "bottom": 0.14, "top": 0.9})


def _unexplained_section(report: dict, out: Path) -> list[str]:
    """What the final model leaves unexplained (``report["unexplained"]``), with a plot of the strongest."""
    entries = report.get("unexplained") or []
    if not entries or report["global_test"]["passed"]:
        return []
    lines = [
        "## Unexplained structure",
        "",
        "The global test fails and the final model's training residual still depends on these variables "
        "(penalised smooth per variable, Bonferroni over the variables):",
        "",
        "| variable | share of the residual | Bonferroni p | form chosen there (BIC) | why it is not an effect |",
        "|---|---:|---:|---|---|",
    ]
    for e in entries:
        form = e.get("form") or {}
        lines.append(
            f"| {e['variable']} | {e['share']:.1%} | {e['p_bonferroni']:.2g} | {form.get('form', '-')} "
            f"(order {form.get('order')}) | {e.get('reason', '-')} |"
        )
    if not entries[0].get("significant", True):  # a smooth no test supports: its curve and band would mislead
        return lines + ["", "No variable is significant on its own, so no smooth is drawn.", ""]
    name = f"unexplained_{entries[0]['variable']}.png"
    plot_unexplained(entries[0], out / name)
    lines += [
        "",
        f"The smooth of the final model's training residual in {entries[0]['variable']}, with a band of two standard "
        "errors: a curve that leaves zero by more than its band is what the model still lacks there (where its "
        "level is not determined, a joint offset the geometry carries, only its shape is drawn, about zero, with the "
        "shape's band: look for where the curve leaves its band, not for its level).",
        "",
        f"![unexplained {entries[0]['variable']}]({name})",
        "",
    ]
    return lines
