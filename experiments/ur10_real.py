"""Calibrate the real UR10 (ipa-robot-accuracy data, Leica tracker + T-Mac) and test across series.

Part 1, per series and method (``auto``, ``kinematic``, ``pcm``, ``kinematic+ann``): ``calibrate``'s own seeded
80/20 split, which keeps the revisits of one joint configuration (joints within ``group_tol``) wholly on one side
(Series B and D measure many configurations twice; a random split would judge a model on a second visit to a pose
it was fitted on); held-out RMSE and max before (nominal geometry, fitted tracker pose and lever arm), after
the geometric fit and at the end, the global test of the last least-squares fit, the runtime.

Part 2, across series: a kinematic calibration on every row of the source series; on the target
series the geometry is kept fixed and only the tracker pose and the lever arm are re-fitted
(:func:`~torchcal.estimate.fit_instrument_and_tool`) on a seeded 20 % of its poses, then the
errors are taken on the other 80 %. The nominal geometry is treated the same way for comparison.
For B <-> C (same tracker placement) the source's tracker pose and lever arm are also used as they
are, with no re-fit.

Series A (11 911 rows) is used whole by default; ``--a-rows`` subsamples it (seeded) for a shorter run.

Usage::

    python scripts/ur10_real.py /path/to/ur10-ipa                    # everything, into runs/ur10/
    python scripts/ur10_real.py /path/to/ur10-ipa --quick --json     # series C, kinematic, and C -> B
    python scripts/ur10_real.py /path/to/ur10-ipa --series B,C --out /tmp/ur10 --threads 1

Writes ``ur10_real.json`` and ``ur10_real.md`` into ``--out``, prints the tables, and with
``--json`` prints the JSON object as the last line of stdout.
"""

from __future__ import annotations

import copy
import json
import math
import time
from pathlib import Path

import torch

from experiments.ipa_series import series_file, subsample
from torchcal.data import Measurements, read_ipa
from torchcal.effects import MeasurementModel
from torchcal.estimate.fit import errors, place_instrument_and_tool
from torchcal.pipeline import Options, calibrate
from torchcal.robot import load_robot

ROBOT = "ur10"
SERIES = ("A", "B", "C", "D")
METHODS = ("auto", "kinematic", "pcm", "kinematic+ann")
PAIRS = (("C", "B"), ("B", "C"), ("C", "D"), ("C", "A"))
SAME_PLACEMENT = {("B", "C"), ("C", "B")}  # README: the home pose agrees within 0.2 mm
SEED = 0
HOLDOUT = 0.2
MM = 1e3


# ----------------------------------------------------------------------------- data


def load_series(data_dir: Path, names, a_rows: int) -> tuple[dict[str, Measurements], dict[str, dict]]:
    data, notes = {}, {}
    for s in names:
        m = read_ipa(series_file(data_dir, s))
        if s == "A":
            m, note = subsample(m, a_rows, SEED)
            if note:
                notes[s] = note
        data[s] = m
    return data, notes


def stats(e: torch.Tensor) -> dict:
    """RMSE and max [mm] of error norms ``e (N,)`` [m]."""
    return {"rmse_mm": float(e.square().mean().sqrt()) * MM, "max_mm": float(e.max()) * MM, "n": int(e.numel())}


# ----------------------------------------------------------------------------- part 1


def within_series(name: str, m: Measurements, method: str) -> dict:
    t0, c0 = time.perf_counter(), time.process_time()
    run = calibrate(ROBOT, m, Options.of(method=method, seed=SEED, holdout=HOLDOUT, trajectory=False))
    runtime, cpu = time.perf_counter() - t0, time.process_time() - c0
    st = {s.name: stats(s.holdout_errors) for s in run.stages}
    fit = run.fits[-1]
    return {
        "series": name,
        "method": method,
        "n_train": int(run.train_idx.numel()),
        "n_holdout": int(run.holdout_idx.numel()),
        "nominal": st["nominal"],
        # pcm fits no geometry: its "geometric" stage is the nominal one, reported as absent
        "geometric": st["geometric"] if method != "pcm" else None,
        "final": stats(run.stages[-1].holdout_errors),
        "final_stage": run.stages[-1].name,
        "global_test": {**fit.global_test, "fit": fit.stage},
        "runtime_s": runtime,
        "cpu_s": cpu,
        # the held-out split: revisit groups kept on one side, and the gross errors screened out
        "split": {
            "grouped": True,
            "merged_groups": int(run.split.merged_groups) if run.split is not None else 0,
            "merged_rows": int(run.split.merged_rows) if run.split is not None else 0,
        },
        # what the closed loop named, each with the held-out RMSE before and after it, and what it dropped
        "stages": [{"name": s.name, "rmse_mm": stats(s.holdout_errors)["rmse_mm"]} for s in run.stages],
        "effects": [
            {
                "kind": e["kind"],
                "joint": e["joint"],
                "label": e.get("label", e["kind"]),
                "rmse_before_mm": e.get("rmse_before_mm"),
                "rmse_after_mm": e.get("rmse_after_mm"),
            }
            for e in run.effects_report
        ],
        "rejected": [{"name": r.get("name", r["kind"]), "reason": r.get("reason", "")} for r in run.rejected],
    }


# ----------------------------------------------------------------------------- part 2


def refit_tracker(model, fit: Measurements):
    """A copy of ``model`` whose tracker pose and lever arm are re-fitted on ``fit`` (geometry fixed)."""
    model = copy.deepcopy(model)
    robot = model.robot
    rms = place_instrument_and_tool(robot, fit.q, fit.p)
    return model, robot.tool.nominal.clone(), rms


def transfer(src: str, dst: str, source_run, target: Measurements) -> dict:
    t0 = time.perf_counter()
    perm = torch.randperm(target.n, generator=torch.Generator().manual_seed(SEED))
    k = int(round(HOLDOUT * target.n))
    fit, ev = target.subset(torch.sort(perm[:k]).values), target.subset(torch.sort(perm[k:]).values)

    nominal = MeasurementModel(load_robot(ROBOT))
    out = {"source": src, "target": dst, "n_source": int(source_run.train_idx.numel()), "n_fit": fit.n, "n_eval": ev.n}
    for key, base in (("nominal_refit", nominal), ("transferred_refit", source_run.model)):
        model, lever, rms = refit_tracker(base, fit)
        out[key] = {
            **stats(errors(model, ev, trajectory=False)),
            "lever_mm": [float(v) * MM for v in lever],
            "fit_rms_mm": rms * MM,
        }
    if (src, dst) in SAME_PLACEMENT:
        lever = source_run.model.robot.tool.vector().detach()
        out["no_refit"] = {
            **stats(errors(source_run.model, ev, trajectory=False)),
            "lever_mm": [float(v) * MM for v in lever],
        }
    else:
        out["no_refit"] = None
    out["runtime_s"] = time.perf_counter() - t0
    return out


def source_calibration(m: Measurements):
    """Kinematic calibration on (practically) every row: calibrate() always keeps one pose out at least."""
    t0 = time.perf_counter()
    run = calibrate(ROBOT, m, Options.of(method="kinematic", seed=SEED, holdout=0.5 / m.n, trajectory=False))
    return run, time.perf_counter() - t0


# ----------------------------------------------------------------------------- output


def _f(x, nd=3) -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{nd}f}"


def _rm(s: dict | None) -> str:
    return "—" if s is None else f"{_f(s['rmse_mm'])} / {_f(s['max_mm'])}"


def markdown(res: dict) -> str:
    lines = ["# UR10 (ipa-robot-accuracy): real-data calibration", ""]
    for s, note in res["subsampled"].items():
        lines.append(f"Series {s} subsampled: {note['rows']} of {note['of']} rows (seed {note['seed']}).")
    lines += [
        f"Split: calibrate's seeded {1 - HOLDOUT:.0%}/{HOLDOUT:.0%} split (seed {SEED}) with the revisits of one "
        "joint configuration kept on one side (grouped). Errors are position error norms, RMSE / max [mm].",
        "",
    ]
    if res["within"]:
        lines += [
            "## Part 1: per series and method (held-out poses)",
            "",
            "| series | method | train/held-out | revisit groups | nominal | geometric | final "
            "| global test s0² (thr, fit) | time [s] |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in res["within"]:
            g = r["global_test"]
            lines.append(
                f"| {r['series']} | {r['method']} | {r['n_train']}/{r['n_holdout']} "
                f"| {r['split']['merged_groups']} ({r['split']['merged_rows']} poses) | {_rm(r['nominal'])} "
                f"| {_rm(r['geometric'])} | {_rm(r['final'])} | {_f(g['statistic'], 1)} "
                f"({_f(g['threshold'])}, {g['fit']}) | {_f(r['runtime_s'], 1)} |"
            )
        looped = [r for r in res["within"] if r["method"] == "auto"]
        if looped:
            lines += [
                "",
                "### What the closed loop (`auto`) found",
                "",
                "| series | stages: held-out RMSE [mm] | dropped or rejected |",
                "|---|---|---|",
            ]
            for r in looped:
                story = " → ".join(f"{st['name']} {_f(st['rmse_mm'])}" for st in r["stages"])
                lines.append(f"| {r['series']} | {story} | {', '.join(x['name'] for x in r['rejected']) or '—'} |")
        lines += [
            "",
            "nominal: nominal geometry with the tracker pose and lever arm fitted on the training poses. "
            "pcm fits no geometry (geometric: —). The global test is that of the last least-squares fit named "
            "(the correction network is not one); s0² is the a-posteriori variance factor, thr its 95 % bound.",
            "",
        ]
    if res["transfer"]:
        lines += [
            "## Part 2: across series (kinematic geometry of the source; tracker pose and lever arm re-fitted "
            f"on {HOLDOUT:.0%} of the target, errors on the other {1 - HOLDOUT:.0%})",
            "",
            "| source → target | fit/eval | nominal geometry, re-fit | transferred geometry, re-fit "
            "| transferred, no re-fit | target self-cal (part 1) | lever length src / re-fit [mm] | time [s] |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in res["transfer"]:
            lever_src = math.hypot(*r["source_lever_mm"])
            lever_dst = math.hypot(*r["transferred_refit"]["lever_mm"])
            lines.append(
                f"| {r['source']} → {r['target']} | {r['n_fit']}/{r['n_eval']} | {_rm(r['nominal_refit'])} "
                f"| {_rm(r['transferred_refit'])} | {_rm(r['no_refit'])} | {_rm(r['target_self'])} "
                f"| {_f(lever_src, 1)} / {_f(lever_dst, 1)} | {_f(r['runtime_s'], 1)} |"
            )
        lines += ["", "Source calibrations (kinematic, all rows but one):"]
        for s, v in res["sources"].items():
            lines.append(f"- {s}: {v['n_train']} poses, {_f(v['runtime_s'], 1)} s")
        lines.append("")
        lines.append(
            "target self-cal: the target's own kinematic calibration from part 1 (its own 20 % held-out "
            "poses, not the same evaluation poses): a reference, not a like-for-like comparison."
        )
        lines.append("")
    lines.append(f"Total runtime: {_f(res['runtime_s'], 1)} s ({res['threads']} torch thread(s))")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- main


def run(
    data_dir: Path,
    names: tuple[str, ...],
    methods: tuple[str, ...],
    pairs: tuple[tuple[str, str], ...],
    a_rows: int,
    quick: bool,
    out: Path,
) -> tuple[dict, str]:
    """Part 1 (each series calibrated on itself with each method) and part 2 (the pairs: calibrate on the first
    series, test on the second); writes ``ur10_real.json`` and ``ur10_real.md`` into ``out``.

    Args:
        data_dir: the ur10-ipa folder (holds Series_A ... Series_D).
        names: series for part 1; methods: the calibrate methods for part 1; pairs: (source, target) series.
        a_rows: subsample Series A to this many rows (0: all).
        quick: recorded in the result (the caller chose the short set).
        out: the output folder (created).

    Returns:
        The result (JSON-ready) and its Markdown tables.
    """
    t_start = time.perf_counter()
    needed = sorted(set(names) | {s for p in pairs for s in p})
    data, subsampled = load_series(data_dir, needed, a_rows)

    within = [within_series(s, data[s], meth) for s in names for meth in methods]
    self_cal = {r["series"]: r["final"] for r in within if r["method"] == "kinematic"}

    sources, runs, transfers = {}, {}, []
    for src, dst in pairs:
        if src not in runs:
            runs[src], dt = source_calibration(data[src])
            sources[src] = {"n_train": int(runs[src].train_idx.numel()), "runtime_s": dt}
        r = transfer(src, dst, runs[src], data[dst])
        r["source_lever_mm"] = [float(v) * MM for v in runs[src].model.robot.tool.vector().detach()]
        r["target_self"] = self_cal.get(dst)
        transfers.append(r)

    res = {
        "robot": ROBOT,
        "data_dir": str(data_dir),
        "seed": SEED,
        "holdout": HOLDOUT,
        "quick": quick,
        "threads": torch.get_num_threads(),
        "subsampled": subsampled,
        "within": within,
        "sources": sources,
        "transfer": transfers,
        "runtime_s": time.perf_counter() - t_start,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "ur10_real.json").write_text(json.dumps(res, indent=2) + "\n")
    md = markdown(res)
    (out / "ur10_real.md").write_text(md)
    return res, md
