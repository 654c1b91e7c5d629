"""A kernel (Gaussian-process mean) correction: local structure in joint space.

What a real arm leaves after its geometry is fitted is often repeatable but local: poses
close in joint space share their residual, poses a few tenths of a radian apart do not (so
on the UR10 data of Landgraf et al.: scripts/ur10_investigate.py measures the correlation of
neighbouring residuals against their distance). A global network like the paper's 6-29-3
cannot follow such short-range structure; kernel regression can. The correction in the base frame is

    dp(q) = sum_i k(q, q_i) alpha_i,   k(q, q') = exp(-|S (q - q')|^2 / (2 l^2)),
    alpha = (K + lambda I)^-1 y,

the posterior mean of a Gaussian process with a squared-exponential kernel, where ``S``
scales each joint by the RMS distance its rotation moves the probe (m/rad), so that the
length scale ``l`` is in metres of probe motion and the same settings suit any robot, and
``lambda`` is the noise-to-signal variance ratio. ``l`` and ``lambda`` are chosen on
validation data (:func:`fit_kernel_correction`).
"""

from __future__ import annotations

import math

import torch

from torchcal._torch import same_version, version_key
from torchcal.effects.base import Context, Effect
from torchcal.stats import paired_improvement  # noqa: F401 (the paired test's old home, kept importable)

Tensor = torch.Tensor

LENGTH_SCALES = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)  # m of probe motion
NOISE_RATIOS = (0.03, 0.1, 0.3, 1.0, 3.0)
MAX_SUPPORT = 3000  # training poses kept as support (a seeded subset beyond that)


class KernelCorrection(Effect):
    """The ``learned`` effect as kernel regression (module docstring); acts in the base frame.

    Args:
        dof: joints.
        n_support: number of support poses (their joints and weights are buffers, so a saved
            model reloads exactly).
    """

    kind = "learned"
    acts_on = "cartesian"
    fades_beyond_region = True

    def __init__(self, dof: int, n_support: int = 0):
        super().__init__(joint=None)
        self.register_buffer("support", torch.zeros(n_support, dof, dtype=torch.float64))
        self.register_buffer("alpha", torch.zeros(n_support, 3, dtype=torch.float64))
        self.register_buffer("metric", torch.ones(dof, dtype=torch.float64))  # S / l per joint
        self.register_buffer("length_scale", torch.tensor(1.0, dtype=torch.float64))
        self.register_buffer("noise_ratio", torch.tensor(1.0, dtype=torch.float64))
        self._cache: tuple | None = None  # (inputs with their versions, output) of the last plain call

    def kernel(self, q: Tensor) -> Tensor:
        return torch.exp(-0.5 * torch.cdist(q * self.metric, self.support * self.metric).square())

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:
        q = ctx.q
        if len(self.support) == 0:
            return torch.zeros(q.shape[0], 3, dtype=q.dtype, device=q.device)
        # The output depends on q and the buffers only, never on a calibration parameter, and a
        # least-squares fit with the kernel in place evaluates it at the same q dozens of times:
        # the last result is reused while q and the buffers are the same tensor objects, unmodified
        # (in-place version counters). Tensors under a torch.func transform are never cached.
        key = None if q.requires_grad else version_key(q, self.support, self.alpha, self.metric)
        if key is None:
            return self.kernel(q) @ self.alpha
        if self._cache is not None and same_version(self._cache[0], key):
            return self._cache[1]
        out = self.kernel(q) @ self.alpha
        if not out.requires_grad:
            self._cache = (key, out)
        return out

    def scale_(self, factor: float) -> None:
        with torch.no_grad():
            self.alpha.mul_(factor)

    def config(self) -> dict:
        return {"dof": int(self.support.shape[1]), "n_support": int(self.support.shape[0])}

    def describe(self) -> dict:
        return {
            "model": "kernel (Gaussian-process mean)",
            "length_scale_m": float(self.length_scale),
            "noise_ratio": float(self.noise_ratio),
            "n_support": int(self.support.shape[0]),
        }


def joint_metric(robot, q: Tensor) -> Tensor:
    """RMS over the poses of ``|dp/dq_j|`` per joint (m/rad): how far each joint moves the probe."""
    with torch.no_grad():
        _, J = robot.probe_jacobian(q)
        return J.norm(dim=1).square().mean(0).sqrt()


def _gram(q: Tensor, metric: Tensor) -> Tensor:
    return torch.exp(-0.5 * torch.cdist(q * metric, q * metric).square())


def _solve(q: Tensor, y: Tensor, metric: Tensor, lam: float, gram: Tensor | None = None) -> Tensor:
    """``(K + lam I)^-1 y``; ``gram``: ``K`` of ``q`` under ``metric`` when already computed (not modified)."""
    K = _gram(q, metric) if gram is None else gram.clone()
    K.diagonal().add_(lam)
    L, info = torch.linalg.cholesky_ex(K)
    if int(info) != 0:
        return torch.linalg.solve(K, y)
    return torch.cholesky_solve(y, L)


def fit_kernel_correction(
    robot,
    q: Tensor,
    y: Tensor,
    *,
    q_val: Tensor,
    y_val: Tensor,
    seed: int = 0,
    length_scales=LENGTH_SCALES,
    noise_ratios=NOISE_RATIOS,
    start: tuple[float, float] | None = None,
    exhaustive: bool = False,
) -> tuple[KernelCorrection, dict]:
    """Choose ``l`` and ``lambda`` on the validation poses, then fit on all of ``q, y`` (+ validation).

    Args:
        q, y: training joints ``(N, dof)`` and corrections ``(N, 3)`` [m, base frame].
        q_val, y_val: validation poses.
        start: ``(l, lambda)`` of an earlier fit to the same kind of data (a refit after the geometry moved a
            little): the grid is searched locally from the nearest setting, moving to the best of the four
            neighbours until none is better (each setting is an ``N x N`` Cholesky factorisation; ``grid`` lists
            the settings tried). Without it the search starts from the best length scale at the middle noise
            ratio (every length scale tried there): the validation error is unimodal enough along the length
            scale, and the noise ratio moves it little, so a third of the grid finds the full grid's choice.
        exhaustive: try every setting of the grid instead (``start`` is then ignored).

    Returns:
        The fitted effect (support = training + validation poses, at most :data:`MAX_SUPPORT`) and a
        dict with the validation RMSE of every setting tried and the per-pose validation errors
        ``val_errors`` of the best one (fitted on ``q, y`` alone).
    """
    scale = joint_metric(robot, torch.cat([q, q_val]))
    g = torch.Generator().manual_seed(int(seed))
    qs, ys = _at_most_support(q, y, g)
    search = _GridSearch(qs, ys, q_val, y_val, scale, length_scales, noise_ratios)
    best, best_errors, grid = search.run(exhaustive, start)
    qa, ya = _at_most_support(torch.cat([q, q_val]), torch.cat([y, y_val]), g)
    eff = KernelCorrection(q.shape[1], len(qa)).to(q.device)
    metric = scale / best["length_scale_m"]
    with torch.no_grad():
        eff.support.copy_(qa)
        eff.metric.copy_(metric)
        eff.alpha.copy_(_solve(qa, ya, metric, best["noise_ratio"]))
        eff.length_scale.fill_(best["length_scale_m"])
        eff.noise_ratio.fill_(best["noise_ratio"])
    return eff, {
        "grid": grid,
        "best": best,
        "metric_m_per_rad": scale.tolist(),
        "val_errors": best_errors,
        "support": len(qa),
        "max_support": MAX_SUPPORT,
        "rmse_unit": "m",
    }


def _at_most_support(q: Tensor, y: Tensor, g: torch.Generator) -> tuple[Tensor, Tensor]:
    """``q, y``, or a seeded random :data:`MAX_SUPPORT` of their rows where they have more."""
    if len(q) <= MAX_SUPPORT:
        return q, y
    idx = torch.randperm(len(q), generator=g)[:MAX_SUPPORT]
    return q[idx], y[idx]


class _GridSearch:
    """The validation RMSE of a kernel correction over the grid of length scales and noise ratios, each setting
    computed once (``tried``), the Gram matrices of the last two length scales kept."""

    def __init__(self, qs, ys, q_val, y_val, scale, length_scales, noise_ratios):
        self.qs, self.ys, self.q_val, self.y_val, self.scale = qs, ys, q_val, y_val, scale
        self.length_scales, self.noise_ratios = length_scales, noise_ratios
        self.grams: dict[int, tuple[Tensor, Tensor]] = {}  # per length scale: K of the support, K(validation, support)
        self.tried: dict[tuple[int, int], tuple[dict, Tensor]] = {}

    def evaluate(self, i: int, j: int) -> float:
        """The validation RMSE [m] of length scale ``i`` and noise ratio ``j``."""
        if (i, j) not in self.tried:
            metric = self.scale / self.length_scales[i]
            if i not in self.grams:
                while len(self.grams) >= 2:  # each is N x N: keep the current length scale's and one more
                    self.grams.pop(next(iter(self.grams)))
                Kv = torch.exp(-0.5 * torch.cdist(self.q_val * metric, self.qs * metric).square())
                self.grams[i] = (_gram(self.qs, metric), Kv)
            K, Kv = self.grams[i]
            e = (self.y_val - Kv @ _solve(self.qs, self.ys, metric, self.noise_ratios[j], gram=K)).norm(dim=-1)
            row = {"length_scale_m": self.length_scales[i], "noise_ratio": self.noise_ratios[j]}
            self.tried[(i, j)] = ({**row, "val_rmse_m": float(e.square().mean().sqrt())}, e)
        return self.tried[(i, j)][0]["val_rmse_m"]

    def _nearest(self, values, v) -> int:
        return min(range(len(values)), key=lambda k: abs(math.log(values[k] / v)))

    def _first(self, exhaustive: bool, start) -> tuple[int, int]:
        """Where the local search starts (see :func:`fit_kernel_correction`'s ``start`` and ``exhaustive``)."""
        if exhaustive:
            for i in range(len(self.length_scales)):
                for j in range(len(self.noise_ratios)):
                    self.evaluate(i, j)
            return min(sorted(self.tried), key=lambda k: self.tried[k][0]["val_rmse_m"])
        if start is None:
            # the length scale matters most (the validation error falls and rises again along it; the noise ratio
            # moves it little): every length scale at the middle noise ratio, then the local search from the best
            j0 = len(self.noise_ratios) // 2
            return (min(range(len(self.length_scales)), key=lambda i: self.evaluate(i, j0)), j0)
        return (self._nearest(self.length_scales, start[0]), self._nearest(self.noise_ratios, start[1]))

    def run(self, exhaustive: bool, start) -> tuple[dict, Tensor, list[dict]]:
        """The best setting's row, its per-pose validation errors, and every setting tried (in the grid's order,
        so that ties go the same way as in a full search)."""
        at = self._first(exhaustive, start)
        while True:
            around = [(at[0] + di, at[1] + dj) for di, dj in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))]
            around = [(i, j) for i, j in around if 0 <= i < len(self.length_scales) and 0 <= j < len(self.noise_ratios)]
            step = min(around, key=lambda ij: self.evaluate(*ij))
            if step == at:
                break
            at = step
        grid = [self.tried[k][0] for k in sorted(self.tried)]
        best_key = min(sorted(self.tried), key=lambda k: self.tried[k][0]["val_rmse_m"])
        best, best_errors = self.tried[best_key]
        return best, best_errors, grid
