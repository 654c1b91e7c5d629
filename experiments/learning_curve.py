"""How many poses does a calibration need? Held-out RMSE against the number of training poses.

For one data set (a UR10 series of Landgraf et al., or a simulated campaign) the held-out poses are fixed:
the split :func:`torchcal.calibrate` itself makes (seeded, 80/20, revisits of one joint configuration kept
on one side). The training poses are put in one seeded random order, and each point of the curve calibrates
on the first ``k`` of them (nested subsets: a larger set holds every smaller one), for each method, and
measures the position error on the fixed held-out poses. ``calibrate`` always keeps one pose of what it is
given out of the fit, so a point fits ``k - 1`` poses (the reports say ``n_fit``); ``"all"`` is every
training pose.

``scripts/learning_curve.py`` runs it and writes ``learning_curve.json``, ``learning_curve.md`` (a table)
and ``learning_curve.png`` (the curves) into its ``--out`` folder.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from experiments.ipa_series import series_file
from torchcal import stats as S
from torchcal.data import Measurements, read_ipa
from torchcal.errors import TorchcalError
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate
from torchcal.pipeline.run import holdout_split

SIZES: tuple[int | str, ...] = (50, 100, 200, 500, 1000, "all")
METHODS = ("kinematic", "auto")
HOLDOUT = 0.2
MM = 1e3


def parse_sizes(text: str) -> tuple[int | str, ...]:
    """``"50,100,all"`` -> ``(50, 100, "all")``; each a positive integer or ``all``."""
    out: list[int | str] = []
    for tok in (t.strip() for t in text.split(",") if t.strip()):
        if tok == "all":
            out.append("all")
            continue
        try:
            k = int(tok)
        except ValueError:
            raise ValueError(f"training size '{tok}' is neither a positive integer nor 'all'") from None
        if k < 2:
            raise ValueError(f"training size {k} is below 2 (calibrate keeps one pose out)")
        out.append(k)
    return tuple(out)


def curve_splits(data: Measurements, seed: int, group_tol: float = S.GROUP_TOL) -> tuple[torch.Tensor, torch.Tensor]:
    """The fixed held-out rows (calibrate's own split of ``data``) and the training rows in their nested order.

    Returns:
        ``(order, test)``: training row indices in a seeded random order ``(n_train,)`` and the held-out row
        indices ``(n_test,)``, both into ``data``.
    """
    split = holdout_split(data, HOLDOUT, seed + S.Stream.HOLDOUT, False, group_tol)
    train, test = split
    g = torch.Generator().manual_seed(int(seed) + 7919)  # its own stream: the order must not move the split
    return train[torch.randperm(len(train), generator=g)], test


def learning_curve(
    robot: str,
    data: Measurements,
    *,
    sizes=SIZES,
    methods=METHODS,
    seed: int = 0,
    name: str = "",
    robot_factory=None,
) -> dict:
    """Held-out RMSE [mm] of each method calibrated on nested training subsets of ``data``.

    Args:
        robot: built-in robot name or description file (loaded afresh for every calibration).
        data: measurements with positions (static poses).
        sizes: training sizes (integers, and ``"all"`` for every training pose); sizes above the number of
            training poses are skipped (``"all"`` covers them).
        methods: ``calibrate`` methods.
        seed: seeds the held-out split, the order of the training poses and the calibrations.
        name: what the data are called in the result.
        robot_factory: optional callable returning a fresh robot model (instead of loading ``robot``).

    Returns:
        ``{"data", "robot", "n_train", "n_test", "seed", "points": [...]}``; each point has ``size`` (as asked),
        ``n_train`` (the subset), ``n_fit`` (what calibrate fitted), ``method``, ``rmse_mm``, ``max_mm``,
        ``median_mm``, ``runtime_s``, ``cpu_s``, ``effects`` (kinds kept), or ``error`` when the calibration
        refused the subset.
    """
    order, test_idx = curve_splits(data, seed)
    test = data.subset(torch.sort(test_idx).values)
    n_train = len(order)
    ks: list[tuple[int | str, int]] = []
    for s in sizes:
        k = n_train if s == "all" else int(s)
        if k > n_train or any(k == kk for _, kk in ks):
            continue
        ks.append((s, k))
    points = []
    for size, k in ks:
        sub = data.subset(torch.sort(order[:k]).values)
        for method in methods:
            points.append(_point(robot, robot_factory, sub, test, size, k, method, seed))
    return {
        "data": name,
        "robot": str(robot),
        "n_train": n_train,
        "n_test": test.n,
        "seed": seed,
        "holdout": HOLDOUT,
        "points": points,
        "rmse_unit": "mm",
    }


def _point(robot, factory, sub: Measurements, test: Measurements, size, k: int, method: str, seed: int) -> dict:
    out = {"size": size, "n_train": k, "method": method}
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        # 0.5 / k: calibrate holds out round(0.5) -> its minimum of one pose; everything else is fitted
        opts = Options.of(method=method, seed=seed, holdout=min(0.5 / k, 0.5), trajectory=False)
        run = calibrate(factory() if factory is not None else robot, sub, opts)
    except TorchcalError as err:  # too few poses for this method: the curve says so and goes on
        return {**out, "error": f"{type(err).__name__}: {err}"}
    with torch.no_grad():
        e = errors(run.model, test, trajectory=False)
    return {
        **out,
        "n_fit": int(run.train_idx.numel()),
        "rmse_mm": S.rmse(e) * MM,
        "max_mm": float(e.max()) * MM,
        "median_mm": float(e.median()) * MM,
        "runtime_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "effects": [r["label"] if r.get("label") else r["kind"] for r in run.effects_report],
    }


# ----------------------------------------------------------------------------- output


def markdown(results: list[dict]) -> str:
    """One table per data set: a row per training size, a column per method (held-out RMSE [mm])."""
    lines = ["# Learning curves: held-out RMSE [mm] against the number of training poses", ""]
    for res in results:
        methods = list(dict.fromkeys(p["method"] for p in res["points"]))
        lines += [
            f"## {res['data'] or 'data'} ({res['robot']}; {res['n_train']} training poses, {res['n_test']} held out, "
            f"grouped split, seed {res['seed']})",
            "",
            "| training poses | " + " | ".join(methods) + " |",
            "|---|" + "---|" * len(methods),
        ]
        for k in dict.fromkeys(p["n_train"] for p in res["points"]):
            label = f"{k} (all)" if k == res["n_train"] else str(k)
            cells = []
            for m in methods:
                p = next(p for p in res["points"] if p["n_train"] == k and p["method"] == m)
                cells.append("failed" if "error" in p else f"{p['rmse_mm']:.3f}")
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def plot(results: list[dict], path: Path) -> None:
    """The curves (log-log: RMSE [mm] against training poses), one line per data set and method, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    styles = {"kinematic": "--", "auto": "-"}
    for res in results:
        for m in dict.fromkeys(p["method"] for p in res["points"]):
            pts = [p for p in res["points"] if p["method"] == m and "error" not in p]
            if not pts:
                continue
            ax.plot(
                [p["n_train"] for p in pts],
                [p["rmse_mm"] for p in pts],
                styles.get(m, ":"),
                marker="o",
                label=f"{res['data'] or 'data'}: {'default (auto)' if m == 'auto' else m}",
            )
    ax.set_xscale("log")
    ax.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter, ScalarFormatter

    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.yaxis.set_major_formatter(FormatStrFormatter("%.3g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%.3g"))
    ax.set_xlabel("training poses")
    ax.set_ylabel("held-out RMSE [mm]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(
    data_dir: Path | None, series: list[str], simulated: int, sizes, methods, seed: int, out: Path
) -> tuple[dict, str]:
    """The curves of the UR10 ``series`` read from ``data_dir`` (or of a simulated UR5 campaign of ``simulated``
    poses), written to ``out`` as learning_curve.json, learning_curve.md and learning_curve.png.

    Returns:
        ``{"results": [...]}`` (:func:`learning_curve` per data set) and the markdown tables.
    """
    results = []
    if simulated:
        data = simulated_data(simulated, seed)
        results.append(learning_curve("ur5", data, sizes=sizes, methods=methods, seed=seed, name="sim"))
    else:
        for s in series:
            m = read_ipa(series_file(data_dir, s))
            results.append(learning_curve("ur10", m, sizes=sizes, methods=methods, seed=seed, name=f"UR10 {s}"))
    out.mkdir(parents=True, exist_ok=True)
    result = {"results": results}
    md = markdown(results)
    (out / "learning_curve.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "learning_curve.md").write_text(md)
    plot(results, out / "learning_curve.png")
    return result, md


def simulated_data(poses: int = 300, seed: int = 0) -> Measurements:
    """A small simulated UR5 campaign with a joint-2 compliance (for a quick curve and the tests)."""
    from torchcal.sim import EffectSpec, SimConfig, simulate

    c = simulate(
        SimConfig(robot="ur5", poses=poses, test_poses=1, seed=seed, effects=[EffectSpec.parse("compliance:2=40um")])
    )
    return c.train
