"""Calibrate the real UR10's series together: one robot, one instrument pose per tracker placement, one lever arm per
tool (issue 26).

The ipa-robot-accuracy series were measured on four days with two T-Mac mounts (about 93 mm for A-C, 342 mm for D).
Merged into one file with a ``station`` column (one per series) and a ``probe`` column (``T1`` for A-C, ``T2`` for D),
they are calibrated together. The data's README calls B's and C's tracker placement the same (their home poses agree
within 0.2 mm), but they were measured on different days, and fitted as two stations (all four series together,
kinematic) their tracker origins lie 0.8 mm apart in the robot's base and B's held-out error drops from 0.516 to 0.497
mm: at this accuracy they are two placements (``--bc-one-station`` merges them, for the comparison).

Held-out rows: each series' own rows held out when it is calibrated alone (``calibrate``'s seeded, revisit-grouped
80/20 split of that series, its gross errors screened as alone), so each series' held-out error of the joint
calibration compares with that series calibrated alone on the very same rows (docs/real-data.md).

Across series (the joint geometry): the joint calibration's model, on a target series, with its station's pose and
its probe's lever arm re-fitted rigidly (robot fixed, :func:`~torchcal.estimate.fit.place_instrument_and_tool`) on a
seeded 20 % of the target's rows and judged on the other 80 % (the protocol of ``scripts/ur10_real.py`` part 2); and
as is, with the target's own station from the joint fit (its held-out rows).

Usage::

    python scripts/ur10_stations.py PATH/TO/ur10-ipa --methods kinematic --json
"""

from __future__ import annotations

import copy
import dataclasses
import time
from pathlib import Path

import torch

from experiments.ipa_series import series_file, subsample
from experiments.ur10_real import HOLDOUT, MM, ROBOT, SEED, refit_tracker
from torchcal import stats as S
from torchcal.data import Measurements, read_ipa
from torchcal.effects import MeasurementModel
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options
from torchcal.pipeline.methods import METHOD_TABLE
from torchcal.pipeline.run import holdout_split, screen_gross_errors, start
from torchcal.robot import load_robot

SERIES = ("A", "B", "C", "D")
METHODS = ("kinematic", "auto")
STATION = {"A": "A", "B": "B", "C": "C", "D": "D"}
#: B and C as the data's README has them: one placement
STATION_BC = {"A": "A", "B": "BC", "C": "BC", "D": "D"}
PROBE = {"A": "T1", "B": "T1", "C": "T1", "D": "T2"}
#: docs/real-data.md: held-out RMSE [mm] of each series calibrated alone (same rows, same split)
ALONE_MM = {
    "kinematic": {"A": 0.436, "B": 0.437, "C": 0.494, "D": 0.415},
    "auto": {"A": 0.096, "B": 0.159, "C": 0.141, "D": 0.208},
}
PAIRS = (("B", "C"), ("C", "B"), ("C", "D"), ("C", "A"))


def _options(method: str) -> Options:
    return Options.of(method=method, seed=SEED, holdout=HOLDOUT, trajectory=False)


def merge(parts: dict[str, Measurements], station_of: dict[str, str] = STATION) -> tuple[Measurements, torch.Tensor]:
    """One measurement set of the series, with ``station`` and ``probe`` columns, and each row's series index.

    Series A has no per-point sigma: its rows take the options' ``sigma_tracker`` (what A alone is weighted with);
    times are left out (B-D have none) and so are the importer's extra columns."""
    names = list(parts)
    stations = tuple(dict.fromkeys(station_of[s] for s in names))
    probes = tuple(dict.fromkeys(PROBE[s] for s in names))
    default = _options("kinematic").fit.sigma_tracker
    sig = [
        m.sigma if m.sigma is not None else torch.full((m.n, 3), default, dtype=torch.float64) for m in parts.values()
    ]
    series = torch.cat([torch.full((m.n,), k, dtype=torch.long) for k, m in enumerate(parts.values())])
    merged = Measurements(
        q=torch.cat([m.q for m in parts.values()]),
        p=torch.cat([m.p for m in parts.values()]),
        temperature=torch.cat([m.temperature for m in parts.values()]),
        sigma=torch.cat(sig),
        meta={"data": "ipa-robot-accuracy", "series": ",".join(names)},
        lines=tuple(line for m in parts.values() for line in m.lines),
        station=torch.tensor([stations.index(station_of[s]) for s in names])[series],
        station_names=stations,
        probe=torch.tensor([probes.index(PROBE[s]) for s in names])[series],
        probe_names=probes,
    )
    return merged, series


def alone_split(m: Measurements) -> tuple[torch.Tensor, torch.Tensor]:
    """The training and held-out rows ``calibrate`` uses for ``m`` alone (split, then its gross errors screened)."""
    opts = _options("kinematic")
    split = holdout_split(m, opts.split.holdout, opts.seed + S.Stream.HOLDOUT, False, opts.split.group_tol)
    tr, ho, _ = screen_gross_errors(load_robot(ROBOT), m, split.keep, split.held, opts, False)
    return tr, ho


def joint_calibration(merged: Measurements, series: torch.Tensor, rows: dict, method: str):
    """The method's stages on ``merged`` with the series' own alone splits as the held-out split."""
    opts = _options(method)
    run = start(ROBOT, merged, dataclasses.replace(opts, levels=dataclasses.replace(opts.levels, outlier=None)))
    offsets = torch.cumsum(torch.bincount(series), 0) - torch.bincount(series)
    tr = torch.cat([rows[k][0] + offsets[k] for k in range(len(rows))])
    ho = torch.cat([rows[k][1] + offsets[k] for k in range(len(rows))])
    run = dataclasses.replace(run, train_idx=torch.sort(tr).values, holdout_idx=torch.sort(ho).values)
    run.model.set_region(merged.q[run.train_idx], fade=METHOD_TABLE[method].fades)
    for stage in METHOD_TABLE[method].stages:
        run = run.apply(stage(run))
    return run


def single(model: MeasurementModel, station: int, probe: int) -> MeasurementModel:
    """``model`` with one station's pose and one probe's lever arm (to re-station rigidly on a target series), without
    a learned correction per station and probe (it describes its own series' day and tool, not the robot's)."""
    from torchcal.effects.grouped import GroupedCorrection
    from torchcal.robot.model import Instrument, Tool

    out = copy.deepcopy(model)
    for i in reversed(range(len(out.effects))):
        if isinstance(out.effects[i], GroupedCorrection):
            del out.effects[i]
    r = out.robot
    with torch.no_grad():
        r.instrument = Instrument(model.robot.T_tracker_base(station).detach())
        r.tool = Tool(model.robot.t_flange_probe(probe).detach())
    return out


def _rmse(e: torch.Tensor) -> float:
    return float(e.square().mean().sqrt()) * MM


def run(data_dir: Path, names, methods, a_rows: int = 0, bc_one_station: bool = False) -> dict:
    parts, notes = {}, {}
    for s in names:
        m = read_ipa(series_file(data_dir, s))
        if s == "A" and a_rows:
            m, note = subsample(m, a_rows, SEED)
            notes[s] = note
        parts[s] = m
    rows = [alone_split(m) for m in parts.values()]
    merged, series = merge(parts, STATION_BC if bc_one_station else STATION)
    out = {"series": list(names), "stations": list(merged.station_names), "probes": list(merged.probe_names)}
    out["subsampled"] = notes
    out["methods"] = {}
    for method in methods:
        t0 = time.perf_counter()
        cal = joint_calibration(merged, series, rows, method)
        runtime = time.perf_counter() - t0
        hold_series = series[cal.holdout_idx]
        per = {}
        for k, s in enumerate(names):
            sel = hold_series == k
            joint = {st.name: _rmse(st.holdout_errors[sel]) for st in cal.stages}
            alone = ALONE_MM.get(method, {}).get(s) if not a_rows or s != "A" else None
            final = _rmse(cal.stages[-1].holdout_errors[sel])
            per[s] = {
                "n_train": int((series[cal.train_idx] == k).sum()),
                "n_holdout": int(sel.sum()),
                "stages_mm": joint,
                "joint_mm": final,
                "alone_mm": alone,
                "ratio": None if alone is None else final / alone,
            }
        across = {}
        for src, dst in PAIRS:
            if src not in parts or dst not in parts:
                continue
            k = names.index(dst)
            target = parts[dst]
            perm = torch.randperm(target.n, generator=torch.Generator().manual_seed(SEED))
            n_fit = int(round(HOLDOUT * target.n))
            fit, ev = target.subset(torch.sort(perm[:n_fit]).values), target.subset(torch.sort(perm[n_fit:]).values)
            st, pr = merged.station[series == k][0], merged.probe[series == k][0]
            model, _, _ = refit_tracker(single(cal.model, int(st), int(pr)), fit)
            across[f"{src}->{dst}"] = {
                "restationed_rmse_mm": _rmse(errors(model, ev, trajectory=False)),
                "as_is_holdout_mm": per[dst]["joint_mm"],
                "n_fit": fit.n,
                "n_eval": ev.n,
                "restation": "rigid instrument pose and lever arm on 20 % of the target, robot fixed",
            }
        rep = _stations(cal)
        out["methods"][method] = {
            "runtime_s": runtime,
            "n_train": int(cal.train_idx.numel()),
            "n_holdout": int(cal.holdout_idx.numel()),
            "holdout_all_mm": _rmse(cal.stages[-1].holdout_errors),
            "per_series": per,
            "across": across,
            "stations": rep,
            "lever_arms_mm": {
                n: [float(v) * MM for v in cal.robot.t_flange_probe(i).detach()] for i, n in enumerate(cal.robot.probes)
            },
            "effects": [e.get("label", e["kind"]) for e in cal.effects_report],
        }
    return out


def _stations(cal) -> dict:
    from torchcal.robot import transforms as tf

    return {
        n: {"tracker_in_base_m": tf.invert(cal.robot.T_tracker_base(i).detach())[:3, 3].tolist()}
        for i, n in enumerate(cal.robot.stations)
    }


def markdown(res: dict) -> str:
    lines = [
        f"# UR10: series {', '.join(res['series'])} calibrated together (stations {', '.join(res['stations'])}; "
        f"probes {', '.join(res['probes'])})",
        "",
    ]
    for method, r in res["methods"].items():
        lines += [
            f"## {method} ({r['runtime_s']:.0f} s, {r['n_train']} / {r['n_holdout']} rows)",
            "",
            "| series | held out | joint [mm] | alone [mm] | joint / alone |",
            "|---|---|---|---|---|",
        ]
        for s, p in r["per_series"].items():
            alone = "-" if p["alone_mm"] is None else f"{p['alone_mm']:.3f}"
            ratio = "-" if p["ratio"] is None else f"{p['ratio']:.2f}"
            lines.append(f"| {s} | {p['n_holdout']} | {p['joint_mm']:.3f} | {alone} | {ratio} |")
        lines += ["", "| across | re-stationed [mm] | own station, held out [mm] |", "|---|---|---|"]
        for k, a in r["across"].items():
            lines.append(f"| {k} | {a['restationed_rmse_mm']:.3f} | {a['as_is_holdout_mm']:.3f} |")
        lines.append("")
    return "\n".join(lines)
