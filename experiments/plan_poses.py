"""Planned against random poses: a pool of measured poses, ``K`` of them chosen by ``torchcal plan`` or at random,
calibrated (``--method kinematic``) and scored on held-out poses; and the error the plan predicted.

The pool and the held-out poses are calibrate's own grouped split of a data set (a UR10 series of Landgraf et al.,
or a simulated campaign's training file, scored on its test file). The plan is made as ``torchcal plan --run`` makes
it: with the model, the stochastic model and the variance factor of a kinematic calibration of the whole pool (what
an earlier campaign gives a user), the candidates being the pool's joint configurations. Each design is then
calibrated on its ``K`` measured rows (all of them fitted: ``refit``) and its held-out RMSE measured. Per seed
(``seeds``), the planner sees a seeded share of the pool (``candidate_share``, half by default: a plan depends on the
candidates it is offered as a random design on its draw) and a random design is drawn from the whole pool; ``reference``
random poses give the baseline the issue names (kinematic with 200 random poses).
"""

from __future__ import annotations

import functools
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from experiments.ipa_series import series_file
from torchcal.data import Measurements, read_ipa
from torchcal.estimate.fit import errors
from torchcal.pipeline import Options, calibrate, holdout_split
from torchcal.sweep import map_tasks
from torchcal.use.plan import PlanOptions, plan_poses

HOLDOUT = 0.2
SEED = 0
MM = 1e3


def _rmse(e: torch.Tensor) -> float:
    return float(e.square().mean().sqrt()) * MM


def fit_and_score(
    robot: str, rows: Measurements, held: Measurements, sigma_tracker: float | None = None, method: str = "kinematic"
) -> float:
    """Held-out RMSE [mm] on ``held`` of a calibration (``method``) on ``rows``: kinematic on all of them, another
    method with the learning curve's options (docs/real-data.md, *How many poses*), its default's baseline."""
    k = rows.n
    # calibrate keeps at least one pose out to score its stages; refit fits the model written on all of them
    kw = {} if sigma_tracker is None else {"sigma_tracker": sigma_tracker}
    kw |= {"refit": True} if method == "kinematic" else {}
    opts = Options.of(method=method, seed=SEED, holdout=min(0.5 / k, 0.5), trajectory=False, **kw)
    run = calibrate(robot, rows, opts)
    return _rmse(errors(run.model, held, trajectory=False))


@dataclass(frozen=True)
class Protocol:
    """What :func:`compare` measures: the design sizes ``ks``, the seeds, the reference design's size (None: none),
    the plan's options (criterion, edge and spread shares: None takes the method's design,
    :meth:`~torchcal.use.plan.PlanOptions.for_method`), the share of the pool the planner is offered per seed and
    the method each design is planned for and calibrated with; ``oracle``: per seed also a design whose spread picks
    follow the held-out poses themselves (``plan --work``), what a planner that knew where it is judged could do."""

    ks: tuple[int, ...]
    seeds: int = 5
    reference: int | None = 200
    edge_share: float | None = None
    criterion: str = "I"
    spread_share: float | None = None
    candidate_share: float = 0.5
    method: str = "kinematic"
    oracle: bool = False


@dataclass(frozen=True)
class _Designs:
    """What every design of :func:`compare` is made from: the pool, the held-out poses, the model and stochastic
    model of the pool's kinematic calibration, the protocol and how many candidates the planner is offered."""

    robot: str
    pool: Measurements
    held: Measurements
    model: object
    protocol: Protocol
    n_cand: int
    s0_sq: float
    sigma_tracker: float
    sigma_joint: float


def _design(d: _Designs, job: tuple[str, int, int]) -> dict:
    """One independent job of :func:`compare`, a task of :func:`torchcal.sweep.map_tasks`: ``("size", k, seed)``
    plans ``k`` poses from the seed's candidates (and, with the protocol's oracle, toward the held-out poses) and
    draws ``k`` random ones, each calibrated and scored; ``("reference", k, seed)`` scores ``k`` random poses."""
    kind, k, s = job
    pr, pool, held = d.protocol, d.pool, d.held
    rnd = torch.randperm(pool.n, generator=torch.Generator().manual_seed(s))[:k]
    random_mm = fit_and_score(d.robot, pool.subset(torch.sort(rnd).values), held, method=pr.method)
    if kind == "reference":
        return {"random": random_mm}
    cand = torch.sort(torch.randperm(pool.n, generator=torch.Generator().manual_seed(1000 + s))[: d.n_cand]).values
    plan_opts = PlanOptions.for_method(
        pr.method,
        k,
        criterion=pr.criterion,
        edge_share=pr.edge_share,
        spread_share=pr.spread_share,
        sigma_tracker=d.sigma_tracker,
        sigma_joint=d.sigma_joint,
        s0_sq=d.s0_sq,
    )
    t1 = time.perf_counter()
    plan = plan_poses(d.model, pool.q[cand], plan_opts)
    out = {"plan_s": time.perf_counter() - t1, "predicted": plan.predicted_rmse * MM, "random": random_mm}
    if pr.oracle:
        toward = plan_poses(d.model, pool.q[cand], plan_opts, work=held.q)
        out["oracle"] = fit_and_score(
            d.robot, pool.subset(torch.sort(cand[toward.index]).values), held, method=pr.method
        )
    out["planned"] = fit_and_score(d.robot, pool.subset(torch.sort(cand[plan.index]).values), held, method=pr.method)
    return out


def _size_row(k: int, jobs: list[dict]) -> dict:
    """The row of design size ``k`` from its seeds' jobs."""
    planned, predicted, rnd = ([j[n] for j in jobs] for n in ("planned", "predicted", "random"))
    oracle = [j["oracle"] for j in jobs if "oracle" in j]
    return {
        "k": k,
        "planned_mm": statistics.median(planned),
        "planned_range_mm": [min(planned), max(planned)],
        "planned_values_mm": planned,
        "predicted_mm": statistics.median(predicted),
        "predicted_over_measured": statistics.median(p / m for p, m in zip(predicted, planned)),
        "random_mm": {"median": statistics.median(rnd), "min": min(rnd), "max": max(rnd), "values": rnd},
        "plan_s": statistics.median(j["plan_s"] for j in jobs),
        **({"oracle_mm": {"median": statistics.median(oracle), "values": oracle}} if oracle else {}),
    }


def compare(
    robot: str,
    pool: Measurements,
    held: Measurements,
    protocol: Protocol,
    workers: int | None = None,
    address: str | None = None,
) -> dict:
    """Planned and random designs of each size in ``protocol.ks`` from ``pool``, scored on ``held`` (module
    docstring); the designs, independent fits, on ``workers`` Ray CPUs or the cluster at ``address``
    (:func:`torchcal.sweep.map_tasks`; default one after another, the same results)."""
    pr = protocol
    t0 = time.perf_counter()
    base = calibrate(robot, pool, Options.of(method="kinematic", seed=SEED, holdout=HOLDOUT, trajectory=False))
    fit = base.fits[-1]
    s0_sq = float(fit.result.sigma0_sq)
    opts_fit = base.options.fit
    sigma_tracker = _sigma_tracker(pool, opts_fit.sigma_tracker)
    design = PlanOptions.for_method(pr.method, 1, edge_share=pr.edge_share, spread_share=pr.spread_share)
    out: dict = {
        "robot": robot,
        "n_pool": pool.n,
        "n_holdout": held.n,
        "variance_factor": s0_sq,
        "pool_kinematic_holdout_mm": _rmse(errors(base.model, held, trajectory=False)),
        "criterion": pr.criterion,
        "method": pr.method,
        **{n: getattr(design, n) for n in ("edge_share", "spread_share", "spread_from", "spread_length")},
        "candidate_share": pr.candidate_share,
        "sizes": [],
    }
    n_cand = max(1, round(pr.candidate_share * pool.n))
    d = _Designs(robot, pool, held, base.model, pr, n_cand, s0_sq, sigma_tracker, opts_fit.sigma_joint)
    jobs = [("size", k, s) for k in pr.ks for s in range(pr.seeds)]
    jobs += [("reference", pr.reference, s) for s in range(pr.seeds)] if pr.reference else []
    done = map_tasks(functools.partial(_design, d), jobs, workers=workers, address=address)
    for i, k in enumerate(pr.ks):
        out["sizes"].append(_size_row(k, done[i * pr.seeds : (i + 1) * pr.seeds]))
    if pr.reference:
        ref = [j["random"] for j in done[len(pr.ks) * pr.seeds :]]
        out["reference"] = {"k": pr.reference, "random_mm": {"median": statistics.median(ref), "values": ref}}
        for row in out["sizes"]:
            row["planned_over_reference"] = row["planned_mm"] / statistics.median(ref)
    out["seconds"] = time.perf_counter() - t0
    return out


def _sigma_tracker(pool: Measurements, default: float) -> float:
    """The plan's tracker noise: the data's own sigmas (their RMS) where they carry them, as the fit used."""
    return default if pool.sigma is None else float(pool.sigma.square().mean().sqrt())


def sequential(
    robot: str,
    pool: Measurements,
    held: Measurements,
    first: int,
    k: int,
    shares: tuple[float, ...],
    seeds: int = 5,
    workers: int | None = None,
    address: str | None = None,
) -> dict:
    """A second campaign planned with the first one's run: per seed, ``first`` random poses calibrated with the
    default method, then ``k - first`` more planned for it (``plan --run``: its model, variance factor and learned
    correction) from a seeded half of the rest, with each of the learned correction's shares of the picks in
    ``shares``; all ``k`` calibrated and scored on ``held``. The seeds, independent, on ``workers`` Ray CPUs or the
    cluster at ``address`` (:func:`torchcal.sweep.map_tasks`; default one after another, the same results)."""
    t0 = time.perf_counter()
    res: dict = {"first": first, "k": k, "seeds": seeds, "by_share": {}}
    task = functools.partial(_sequential_seed, robot, pool, held, first, k, shares)
    for per_share in map_tasks(task, range(seeds), workers=workers, address=address):
        for share, (mm, n_learned) in per_share.items():
            entry = res["by_share"].setdefault(str(share), {"values_mm": [], "n_learned": []})
            entry["values_mm"].append(mm)
            entry["n_learned"].append(n_learned)
    for entry in res["by_share"].values():
        entry["median_mm"] = statistics.median(entry["values_mm"])
    res["seconds"] = time.perf_counter() - t0
    return res


def _sequential_seed(
    robot: str, pool: Measurements, held: Measurements, first: int, k: int, shares: tuple[float, ...], s: int
) -> dict:
    """Seed ``s`` of :func:`sequential`: per share, the held-out RMSE [mm] and the learned correction's picks."""
    idx = torch.randperm(pool.n, generator=torch.Generator().manual_seed(s))
    done, rest = idx[:first], idx[first:]
    half = torch.randperm(len(rest), generator=torch.Generator().manual_seed(1000 + s))[: len(rest) // 2]
    cand = torch.sort(rest[half]).values
    opts = Options.of(method="auto", seed=SEED, holdout=min(0.5 / first, 0.5), trajectory=False)
    run = calibrate(robot, pool.subset(torch.sort(done).values), opts)
    s0_sq = float(run.fits[-1].result.sigma0_sq)
    noise = {"sigma_tracker": _sigma_tracker(pool, run.options.fit.sigma_tracker)}
    noise["sigma_joint"] = run.options.fit.sigma_joint
    out = {}
    for share in shares:
        plan_opts = PlanOptions.for_method("auto", k - first, learned_share=share, s0_sq=s0_sq, **noise)
        plan = plan_poses(run.model, pool.q[cand], plan_opts)
        rows = pool.subset(torch.sort(torch.cat([done, cand[plan.index]])).values)
        out[share] = (fit_and_score(robot, rows, held, method="auto"), int(plan.learned.sum()))
    return out


def split(m: Measurements) -> tuple[Measurements, Measurements]:
    """Calibrate's own grouped split of ``m`` (seed 0, 20 % held out): the pool and the held-out poses."""
    sp = holdout_split(m, HOLDOUT, SEED, trajectory=False)
    return m.subset(torch.sort(sp.keep).values), m.subset(torch.sort(sp.held).values)


def sequential_markdown(res: dict) -> str:
    lines = [f"| learned share | held-out RMSE [mm], median (values) over {res['seeds']} seeds |", "|---:|---|"]
    for share, e in res["by_share"].items():
        lines.append(f"| {share} | {e['median_mm']:.4f} ({', '.join(f'{v:.4f}' for v in e['values_mm'])}) |")
    return "\n".join(lines)


def run_sequential(
    data_dir: Path, series: str, first: int, k: int, shares: tuple[float, ...], seeds: int, **sweep
) -> dict:
    """:func:`sequential` on a UR10 series' training split, scored on its held-out split; ``sweep``: its
    ``workers`` and ``address``."""
    pool, held = split(read_ipa(series_file(data_dir, series)))
    return {"series": f"Series {series}", **sequential("ur10", pool, held, first, k, shares, seeds, **sweep)}


def run(data_dir: Path, series: str, protocol: Protocol, **sweep) -> dict:
    """:func:`compare` on a UR10 series: the pool its training split's rows, scored on its held-out split;
    ``sweep``: :func:`compare`'s ``workers`` and ``address``."""
    pool, held = split(read_ipa(series_file(data_dir, series)))
    return {"series": f"Series {series}", **compare("ur10", pool, held, protocol, **sweep)}


def simulated(robot: str, protocol: Protocol, poses: int = 2000, test_poses: int = 500, seed: int = 3, **sweep) -> dict:
    """:func:`compare` on a simulated campaign (no effects beyond the geometry): the pool its training file, scored
    on its test file; ``sweep``: :func:`compare`'s ``workers`` and ``address``."""
    from torchcal.sim import SimConfig, simulate

    c = simulate(SimConfig(robot=robot, poses=poses, test_poses=test_poses, seed=seed))
    res = compare(robot, c.train, c.test, protocol, **sweep)
    return {"series": f"simulated {robot} (seed {seed})", **res}


def markdown(res: dict) -> str:
    ref = res.get("reference")
    lines = [
        f"{res.get('series', '?')}: pool {res['n_pool']} poses, {res['n_holdout']} held out; variance factor "
        f"{res['variance_factor']:.3g}; criterion {res['criterion']}, edge share {res['edge_share']}, spread share "
        f"{res['spread_share']} from pick {res.get('spread_from', 0)}; the planner offered "
        f"{res['candidate_share']:.0%} of the pool per seed; method "
        f"{res.get('method', 'kinematic')}; "
        f"kinematic on the whole pool {res['pool_kinematic_holdout_mm']:.4f} mm",
        "",
        "| K | planned median [mm] (min-max) | predicted [mm] | pred/meas | random median [mm] (min-max) | "
        + "planned / random "
        + (f"{ref['k']} |" if ref else "|"),
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for r in res["sizes"]:
        rm = r["random_mm"]
        lines.append(
            f"| {r['k']} | {r['planned_mm']:.4f} ({r['planned_range_mm'][0]:.4f}-{r['planned_range_mm'][1]:.4f}) | "
            f"{r['predicted_mm']:.4f} | {r['predicted_over_measured']:.2f} | "
            f"{rm['median']:.4f} ({rm['min']:.4f}-{rm['max']:.4f}) | "
            + (f"{r['planned_over_reference']:.3f} |" if ref else "|")
        )
    if ref:
        lines += ["", f"reference: {ref['k']} random poses, median {ref['random_mm']['median']:.4f} mm"]
    for r in res["sizes"]:
        if "oracle_mm" in r:
            vals = ", ".join(f"{v:.4f}" for v in r["oracle_mm"]["values"])
            lines += ["", f"K = {r['k']}, spread picks following the held-out poses (oracle): {vals} mm"]
    return "\n".join(lines)
