"""The learned stage measured alone: geometry, the dense kernel correction and the sparse additive + ARD GP
on the residuals of a kinematic fit (``scripts/learned_stage.py`` prints the result as JSON).

Cases: simulated UR5 campaigns (a 0.3 mrad third harmonic on joint 5, written with plain formulas, and a
smooth field), and the real UR10 series (ipa-robot-accuracy) on a split that keeps revisits apart (rows
whose joints agree within a tolerance are on one side). Each model is fitted on the training residuals;
the held-out RMSE, the fit time and the peak resident memory during the fit are reported.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import torch

from torchcal.effects.base import Context
from torchcal.effects.gp import GPSettings, fit_gp_correction
from torchcal.effects.kernel import fit_kernel_correction

F64 = torch.float64
MM = 1e3


class PeakRSS:
    """Peak resident memory of this process while the block runs, sampled every 10 ms [MB above the start]."""

    def __enter__(self):
        self.start = self.peak = _rss()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self):
        while not self._stop.wait(0.01):
            self.peak = max(self.peak, _rss())

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss())
        self.mb = (self.peak - self.start) / 2**20


def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def grouped_split(
    q: torch.Tensor, holdout: float, seed: int, tol: float = 1e-3
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Training and held-out indices with rows whose joints agree within ``tol`` (max abs) on one side.

    Returns the sorted training and held-out indices and the number of rows merged into a group with another.
    """
    n = len(q)
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(0, n, 2048):
        d = torch.cdist(q[i : i + 2048], q, p=float("inf"))
        rows, cols = torch.nonzero(d <= tol, as_tuple=True)
        for a, b in zip((rows + i).tolist(), cols.tolist()):
            if a < b:
                ra, rb = find(a), find(b)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    roots = torch.tensor([find(i) for i in range(n)])
    uniq, inv, counts = torch.unique(roots, return_inverse=True, return_counts=True)
    merged = int(counts[counts > 1].sum())
    perm = torch.randperm(len(uniq), generator=torch.Generator().manual_seed(int(seed)))
    held_groups, size = [], 0
    for gi in perm.tolist():
        if size >= holdout * n:
            break
        held_groups.append(gi)
        size += int(counts[gi])
    held = torch.zeros(len(uniq), dtype=torch.bool)
    held[held_groups] = True
    mask = held[inv]
    return torch.nonzero(~mask).flatten(), torch.nonzero(mask).flatten(), merged


def _kinematic(robot_spec: str, train):
    """The kinematic calibration of ``train`` (the pipeline's ``kinematic`` method; 1 % of it held out there)."""
    from torchcal.pipeline import Options, calibrate

    return calibrate(robot_spec, train, Options.of(method="kinematic", holdout=0.01)).model


def residuals(model, m) -> torch.Tensor:
    """What the model misses, in the robot base frame ``(N, 3)`` [m] (as the pipeline's ``corrections``)."""
    with torch.no_grad():
        return (m.p - model(Context.from_measurements(m, trajectory=False))) @ model.robot.T_tracker_base()[:3, :3]


def _compare_on(model, train, test, seed: int, **kw) -> dict:
    """:func:`compare` on what ``model`` misses on ``train`` and on ``test``."""
    ctx_tr, ctx_te = Context(q=train.q), Context(q=test.q)
    return compare(model.robot, ctx_tr, residuals(model, train), ctx_te, residuals(model, test), seed=seed, **kw)


def _compare_after_kinematic(robot_spec: str, train, test, seed: int, **kw) -> dict:
    """:func:`compare` on the residuals of the kinematic calibration of ``train``."""
    return _compare_on(_kinematic(robot_spec, train), train, test, seed, **kw)


def _rmse(e: torch.Tensor) -> float:
    return float(e.norm(dim=-1).square().mean().sqrt()) * MM


def compare(
    robot,
    ctx_tr: Context,
    y_tr: torch.Tensor,
    ctx_te: Context,
    y_te: torch.Tensor,
    *,
    seed: int = 0,
    methods=("geometry", "kernel", "gp"),
    gp_settings: GPSettings | None = None,
) -> dict:
    """Held-out RMSE [mm], fit time [s] and peak memory [MB] of each learned model on the same residuals."""
    out = {}
    if "geometry" in methods:
        out["geometry"] = {"heldout_rmse_mm": _rmse(y_te), "train_rmse_mm": _rmse(y_tr)}
    if "kernel" in methods:
        # as the pipeline's learned stage: 80 % to fit, 20 % to choose the grid point, then all as support
        perm = torch.randperm(len(y_tr), generator=torch.Generator().manual_seed(seed + 2))
        nv = max(3, int(0.2 * len(y_tr)))
        fi, va = perm[nv:], perm[:nv]
        t0 = time.perf_counter()
        with PeakRSS() as mem:
            eff, info = fit_kernel_correction(
                robot, ctx_tr.q[fi], y_tr[fi], q_val=ctx_tr.q[va], y_val=y_tr[va], seed=seed
            )
        wall = time.perf_counter() - t0
        with torch.no_grad():
            pred = eff(robot, ctx_te)
        out["kernel"] = {
            "heldout_rmse_mm": _rmse(y_te - pred),
            "fit_s": wall,
            "peak_mb": mem.mb,
            "support": info["support"],
            "best": info["best"],
        }
    if "gp" in methods:
        s = gp_settings or GPSettings(seed=seed)
        t0 = time.perf_counter()
        with PeakRSS() as mem:
            eff, info = fit_gp_correction(ctx_tr, y_tr, s)
        wall = time.perf_counter() - t0
        with torch.no_grad():
            mean, sd = eff.predict(ctx_te, noise=True)
        out["gp"] = {
            "heldout_rmse_mm": _rmse(y_te - mean),
            "fit_s": wall,
            "peak_mb": mem.mb,
            "coverage_2sigma": float(((y_te - mean).abs() <= 2 * sd).double().mean()),
            "variable_share": info["variable_share"],
            "n_inducing": info["n_inducing"],
            "exact": info["exact"],
            "evidence_evaluations": info["evidence_evaluations"],
            "additive_length_scale": info["additive_length_scale"],
            "ard_length_scale": info["ard_length_scale"],
        }
    if "gpytorch" in methods:
        out["gpytorch"] = gpytorch_sgpr(ctx_tr, y_tr, ctx_te, y_te, seed=seed)
    return out


def simulated_case(case: str, seed: int = 0, poses: int = 800, test_poses: int = 400, **kw) -> dict:
    """A UR5 campaign with ``case`` = ``"harmonic3"`` (0.3 mrad third harmonic on joint 5) or ``"field"``."""
    from torchcal.sim import campaign as sim

    effects = [sim.EffectSpec.parse("field")] if case == "field" else []
    c = sim.simulate(sim.SimConfig(robot="ur5", poses=poses, test_poses=test_poses, seed=seed, effects=effects))
    train, test = c.train, c.test
    if case == "harmonic3":
        # plain formula: joint 5 reads 0.3 mrad sin(3 q5 + 0.7) less than it is; the probe moves accordingly
        q = c.q_true
        dq = torch.zeros_like(q)
        dq[:, 4] = 3e-4 * torch.sin(3 * q[:, 4] + 0.7)
        with torch.no_grad():
            extra = c.model(Context(q=q + dq)) - c.model(Context(q=q))
        n = train.n
        train = _with_p(train, train.p + extra[:n])
        test = _with_p(test, test.p + extra[n:])
    elif case != "field":
        raise ValueError(f"case '{case}' is not harmonic3 or field")
    res = _compare_after_kinematic("ur5", train, test, seed, **kw)
    return {"case": case, "robot": "ur5", "train": train.n, "test": test.n, "seed": seed, **res}


def _with_p(m, p):
    import dataclasses

    return dataclasses.replace(m, p=p)


def real_case(data_dir: str | Path, series: str, seed: int = 0, holdout: float = 0.2, tol: float = 1e-3, **kw) -> dict:
    """A UR10 series on a grouped 80/20 split (:func:`grouped_split`), residuals of the kinematic fit."""
    from torchcal.data import read_ipa

    files = sorted((Path(data_dir) / f"Series_{series}").glob("measurements_*.csv"))
    m = read_ipa(files[0])
    tr, ho, merged = grouped_split(m.q, holdout, seed, tol)
    train, test = m.subset(tr), m.subset(ho)
    t0 = time.perf_counter()
    model = _kinematic("ur10", train)
    kin_s = time.perf_counter() - t0
    res = _compare_on(model, train, test, seed, **kw)
    return {
        "case": f"ur10-{series}",
        "train": train.n,
        "test": test.n,
        "rows_merged_in_groups": merged,
        "kinematic_fit_s": kin_s,
        "seed": seed,
        **res,
    }


def gpytorch_sgpr(
    ctx_tr: Context,
    y_tr: torch.Tensor,
    ctx_te: Context,
    y_te: torch.Tensor,
    *,
    n_inducing: int = 500,
    iterations: int = 100,
    seed: int = 0,
) -> dict:
    """The same model in gpytorch (optional; not a dependency): per-joint RBF components plus an ARD RBF, an
    ``InducingPointKernel`` (SGPR, Titsias's bound) with k-means inducing inputs that Adam moves as well, each
    output its own GP on the standardised residuals; the held-out RMSE [mm], fit time [s] and peak memory [MB]."""
    import gpytorch

    from torchcal.effects.gp import kmeans

    x, xs = ctx_tr.q, ctx_te.q
    mu, sd = y_tr.mean(0), y_tr.std(0)
    g = torch.Generator().manual_seed(seed)
    z0 = kmeans(x, min(n_inducing, len(x)), g)
    lik_list, models = [], []

    class SGPR(gpytorch.models.ExactGP):
        def __init__(self, tx, ty, lik):
            super().__init__(tx, ty, lik)
            self.mean_module = gpytorch.means.ZeroMean()
            parts = [gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(active_dims=[j])) for j in range(6)]
            parts.append(gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=6)))
            base = gpytorch.kernels.AdditiveKernel(*parts)
            self.covar_module = gpytorch.kernels.InducingPointKernel(base, inducing_points=z0.clone(), likelihood=lik)

        def forward(self, xx):
            return gpytorch.distributions.MultivariateNormal(self.mean_module(xx), self.covar_module(xx))

    t0 = time.perf_counter()
    with PeakRSS() as mem:
        for k in range(3):
            lik = gpytorch.likelihoods.GaussianLikelihood().double()
            model = SGPR(x, (y_tr[:, k] - mu[k]) / sd[k], lik).double()
            model.train()
            lik.train()
            opt = torch.optim.Adam(model.parameters(), lr=0.05)
            mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, model)
            for _ in range(iterations):
                opt.zero_grad()
                loss = -mll(model(x), model.train_targets)
                loss.backward()
                opt.step()
            models.append(model)
            lik_list.append(lik)
    wall = time.perf_counter() - t0
    pred = torch.zeros_like(y_te)
    with torch.no_grad(), gpytorch.settings.fast_pred_var():
        for k, model in enumerate(models):
            model.eval()
            lik_list[k].eval()
            pred[:, k] = model(xs).mean * sd[k] + mu[k]
    return {
        "heldout_rmse_mm": _rmse(y_te - pred),
        "fit_s": wall,
        "peak_mb": mem.mb,
        "n_inducing": len(z0),
        "iterations": iterations,
        "version": gpytorch.__version__,
    }


def scale_case(n: int, seed: int = 0, gp_settings: GPSettings | None = None) -> dict:
    """Fit time and peak memory of the GP on ``n`` synthetic poses (a smooth field plus a one-joint harmonic,
    20 um noise), and its RMSE against the noise-free field on 2000 more poses [mm]."""
    g = torch.Generator().manual_seed(seed)
    q = (torch.rand(n + 2000, 6, generator=g, dtype=F64) * 2 - 1) * 3
    f = 1e-4 * torch.stack(
        [torch.sin(2 * q[:, 1]) * torch.cos(q[:, 2]), torch.cos(2 * q[:, 0]), torch.sin(3 * q[:, 4])], 1
    )
    y = f + 2e-5 * torch.randn(n + 2000, 3, generator=g, dtype=F64)
    t0 = time.perf_counter()
    with PeakRSS() as mem:
        eff, info = fit_gp_correction(Context(q=q[:n]), y[:n], gp_settings or GPSettings(seed=seed))
    wall = time.perf_counter() - t0
    with torch.no_grad():
        pred = eff(None, Context(q=q[n:]))
    return {
        "case": f"synthetic-{n}",
        "fit_s": wall,
        "peak_mb": mem.mb,
        "n_inducing": info["n_inducing"],
        "field_rmse_mm": _rmse(f[n:]),
        "error_vs_field_mm": _rmse(pred - f[n:]),
    }


def run_cases(cases, data_dir: str | Path, seed: int, methods: tuple[str, ...], gp_settings: GPSettings) -> dict:
    """Each case of ``cases`` in turn: ``synthetic-N`` (:func:`scale_case`), ``harmonic3`` or ``field``
    (:func:`simulated_case`), or a UR10 series name (:func:`real_case` on ``data_dir``)."""
    out = []
    for case in cases:
        if case.startswith("synthetic-"):
            out.append(scale_case(int(case.split("-", 1)[1]), seed, gp_settings))
        elif case in ("harmonic3", "field"):
            out.append(simulated_case(case, seed, methods=methods, gp_settings=gp_settings))
        else:
            out.append(real_case(data_dir, case, seed, methods=methods, gp_settings=gp_settings))
    return {"torch_threads": torch.get_num_threads(), "results": out}
