"""Levenberg-Marquardt least squares in torch, with the adjustment statistics.

Legend: ``x`` parameters, ``r(x)`` whitened residuals (``L^-1 (f(x) - l)`` with ``Sigma_ll = L L^T``),
``J = dr/dx``, ``N = J^T J`` the normal matrix, ``lambda`` Marquardt's damping on ``diag(N)``.
The a-posteriori variance factor is ``s0^2 = r^T r / (n - u)`` (Ghilani & Wolf, Adjustment
Computations, ch. 11); parameter covariance ``s0^2 N^-1``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

import torch

from torchcal._threads import torch_threads
from torchcal.errors import EstimationError

Tensor = torch.Tensor


class FitStatus(str, Enum):
    """How a least-squares or network fit ended (str-valued: ``report.json`` writes the plain name).

    The solvers (:func:`levenberg_marquardt`, :mod:`~torchcal.estimate.netfit`) return these.
    """

    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    DIVERGED = "diverged"
    FAILED_SOLVE = "failed_solve"

    def __str__(self) -> str:
        return self.value


STATUSES = tuple(s.value for s in FitStatus)

#: a fit whose normal matrix is singular in at least :data:`SINGULAR_MIN` of its first :data:`SINGULAR_WINDOW`
#: iterations ends as ``failed_solve`` there (:func:`levenberg_marquardt`)
SINGULAR_WINDOW = 6
SINGULAR_MIN = 4
#: the Jacobi-scaled normal matrix (unit diagonal) counts as singular there when its smallest eigenvalue is below
#: this (its Cholesky factorisation fails once this is subtracted from the diagonal): an exact null space leaves
#: eigenvalues of a few 1e-15 of either sign, and whether the factorisation of the matrix itself then fails or ends
#: with small pivots is a matter of rounding (a change in the last bits of the kinematics can then turn a
#: rank-deficient fit of a few iterations into one that runs to its iteration limit)
SINGULAR_EIGENVALUE = 1e-13


@dataclass
class LMResult:
    """What a least-squares solve returns; ``status`` says how it ended."""

    status: FitStatus
    iterations: int
    x: Tensor
    cost_history: list[float]
    names: list[str] = field(default_factory=list)
    n_obs: int = 0
    message: str = ""
    normal: Tensor | None = None  # N = J^T J at the solution
    residuals: Tensor | None = None  # whitened, at the solution
    jacobian: Tensor | None = None  # whitened, at the solution
    #: per residual, the factor its square counts with in the variance factor (None: 1): rows the estimate weighs
    #: below their stochastic model (a 6-D probe's orientations, ``fit.ORIENTATION_LEAD``) count there at the model's
    #: weight, so that ``s0^2`` and the covariance stay those of the stochastic model
    variance_weights: Tensor | None = None

    @property
    def redundancy(self) -> int:
        return self.n_obs - len(self.x)

    @property
    def sigma0_sq(self) -> float:
        """A-posteriori variance factor ``r^T r / (n - u)`` (1 when the stochastic model fits)."""
        if self.residuals is None or self.redundancy <= 0:
            return float("nan")
        r2 = self.residuals.square()
        if self.variance_weights is not None:
            r2 = r2 * self.variance_weights
        return float(r2.sum()) / self.redundancy

    @property
    def cofactor(self) -> Tensor:
        """``N^-1`` via the Cholesky factor of the Jacobi-scaled ``N`` (unit diagonal, so metres and
        radians do not ruin the conditioning); raises :class:`EstimationError` when N is singular."""
        s = _jacobi(self.normal)
        L, info = torch.linalg.cholesky_ex(self.normal * s[:, None] * s[None, :])
        if int(info) != 0:
            raise EstimationError("the normal matrix is not positive definite: parameters are not all identifiable")
        return torch.cholesky_inverse(L) * s[:, None] * s[None, :]

    @property
    def covariance(self) -> Tensor:
        """A-posteriori parameter covariance ``s0^2 N^-1``."""
        return self.sigma0_sq * self.cofactor

    @property
    def std(self) -> Tensor:
        return self.covariance.diagonal().clamp(min=0).sqrt()

    @property
    def correlation(self) -> Tensor:
        Q = self.cofactor
        d = Q.diagonal().clamp(min=1e-300).sqrt()
        return Q / d[:, None] / d[None, :]

    def largest_correlations(self, k: int = 10) -> list[dict]:
        C = self.correlation
        iu = torch.triu_indices(len(C), len(C), offset=1)
        vals = C[iu[0], iu[1]]
        order = torch.argsort(vals.abs(), descending=True)[:k]
        return [{"a": self.names[int(iu[0, i])], "b": self.names[int(iu[1, i])], "rho": float(vals[i])} for i in order]

    def standardized_residuals(self) -> Tensor:
        """``w_i = v_i / sqrt(q_vv,ii)`` with ``Q_vv = I - J N^-1 J^T`` for whitened residuals.

        Each is N(0, 1) under the model; Baarda's data snooping flags |w| > 3.29 (alpha = 0.001).
        """
        Q = self.cofactor
        h = ((self.jacobian @ Q) * self.jacobian).sum(-1)  # leverage, diag(J N^-1 J^T)
        return self.residuals / (1.0 - h).clamp(min=1e-12).sqrt()


def _jacobi(N: Tensor) -> Tensor:
    """Scale factors ``1 / sqrt(diag N)`` (1 where a column is zero)."""
    d = N.diagonal()
    return torch.where(d > 0, d.clamp(min=1e-300).rsqrt(), torch.ones_like(d))


def _singular(Ns: Tensor) -> bool:
    """Whether the Jacobi-scaled normal matrix ``Ns`` (unit diagonal) has an eigenvalue below
    :data:`SINGULAR_EIGENVALUE` (its Cholesky factorisation fails once that is taken off the diagonal)."""
    eye = torch.eye(len(Ns), dtype=Ns.dtype, device=Ns.device)
    return int(torch.linalg.cholesky_ex(Ns - SINGULAR_EIGENVALUE * eye)[1]) != 0


def chi2_quantile(p: float, dof: int) -> float:
    """Quantile of the chi-square distribution (Wilson-Hilferty; relative error < 1e-3 for dof >= 10)."""
    if dof <= 0:
        return float("nan")
    z = float(torch.special.ndtri(torch.tensor(p, dtype=torch.float64)))
    a = 2.0 / (9.0 * dof)
    return dof * (1.0 - a + z * math.sqrt(a)) ** 3


def global_test(result: LMResult, alpha: float = 0.05) -> dict:
    """Global test of the adjustment: ``s0^2 / sigma0^2`` (a-priori 1) against ``chi2_{1-alpha, r} / r``."""
    r = result.redundancy
    stat = result.sigma0_sq
    thr = chi2_quantile(1.0 - alpha, r) / r if r > 0 else float("nan")
    return {"statistic": stat, "threshold": thr, "passed": bool(stat <= thr), "alpha": alpha, "redundancy": r}


def _attempt(fun, x: Tensor, cost: float, Ns: Tensor, gs: Tensor, s: Tensor, damping: float):
    """One damped Gauss-Newton step in Jacobi-scaled variables; ``(cost, damping, dx, r)`` if it does not raise
    the cost, else None."""
    L, info = torch.linalg.cholesky_ex(Ns + damping * torch.eye(len(x), dtype=x.dtype, device=x.device))
    if int(info) != 0:
        return None
    dx = s * -torch.cholesky_solve(gs[:, None], L)[:, 0]
    r = fun(x + dx).detach()
    c = 0.5 * float(r.square().sum())
    return (c, damping, dx, r) if math.isfinite(c) and c <= cost else None


#: the dampings each iteration tries, as factors of the current one (:func:`levenberg_marquardt`)
LADDER = (1e-3, 1e-2, 1e-1, 1.0, 10.0)


class _Trials:
    """The residuals of ``fun`` at several points ``(k, u) -> (k, n)``: one ``torch.func.vmap`` call where ``fun``
    supports it (each operation then runs once over the k points: the five trial points of an iteration cost about
    two or three evaluations instead of five), else one call per point, from the first failure on. The values are
    the same to rounding (a batched product may sum in another order)."""

    def __init__(self, fun):
        self.fun = fun
        self.batched = True

    def __call__(self, X: Tensor) -> Tensor:
        if self.batched and len(X) > 1:
            try:
                return torch.func.vmap(self.fun)(X).detach()
            except Exception:  # noqa: BLE001 - whatever vmap cannot batch (an in-place write, a data-dependent branch)
                self.batched = False
        return torch.stack([self.fun(x).detach() for x in X])


def _ladder(trials: _Trials, x: Tensor, cost: float, Ns: Tensor, gs: Tensor, s: Tensor, lam: float):
    """The damped steps at the dampings ``lam * LADDER`` (one batched factorisation, one batched evaluation of the
    trial points); ``(cost, damping, dx, r)`` of the one with the lowest cost not above ``cost``, else None."""
    dampings = [lam * f for f in LADDER]
    eye = torch.eye(len(x), dtype=x.dtype, device=x.device)
    L, info = torch.linalg.cholesky_ex(Ns + torch.tensor(dampings, dtype=x.dtype, device=x.device)[:, None, None] * eye)
    ok = [k for k in range(len(dampings)) if int(info[k]) == 0]
    if not ok:
        return None
    dx = s * -torch.cholesky_solve(gs[:, None].expand(len(ok), -1, 1), L[ok])[..., 0]
    R = trials(x + dx)
    best = None
    for i, k in enumerate(ok):
        c = 0.5 * float(R[i].square().sum())
        if math.isfinite(c) and c <= cost and (best is None or c < best[0]):
            best = (c, dampings[k], dx[i], R[i])
    return best


def levenberg_marquardt(
    fun: Callable[[Tensor], Tensor],
    x0: Tensor,
    *,
    names: list[str] | None = None,
    max_iter: int = 100,
    xtol: float = 1e-10,
    ftol: float = 1e-14,
    lam0: float = 1e-3,
    jacobian: Callable[[Tensor], Tensor] | None = None,
    stat_tol: float = 0.0,
    callback=None,
    threads: int | None = 1,
    solution_jacobian: bool = True,
) -> LMResult:
    """Minimise ``0.5 |fun(x)|^2`` by Levenberg-Marquardt.

    The normal equations are Jacobi-scaled to a unit diagonal before the damped Cholesky solve
    (parameters in metres and radians, whitened by micrometre noise, span 20 orders of
    magnitude otherwise), and every iteration tries a ladder of dampings around the
    current one and keeps the step with the lowest cost.

    Args:
        fun: ``x (u,) -> r (n,)`` whitened residuals, differentiable by ``torch.func``.
        x0: start ``(u,)`` float64.
        jacobian: ``x -> J (n, u)``; default ``fun.jacobian`` when ``fun`` carries one
            (:func:`~torchcal.estimate.problem.residual_function` does), else ``torch.func.jacfwd(fun)``.
        max_iter: iterations (each one Jacobian).
        xtol: stop when every step component is below ``xtol`` times (|x| + its scale ``1/sqrt(N_ii)``).
        ftol: stop when the relative cost reduction of an accepted step is below ``ftol``.
        stat_tol: stop when a step lowers the cost by less than ``stat_tol`` times the current variance
            factor (at least 1): such a change is statistically invisible, and fits of real data with
            unmodelled errors otherwise creep for hundreds of iterations along flat valleys.
        threads: torch threads for the solve (the caller's are restored after it); None keeps the caller's.
            The kernels are small (u x u solves, one pass over the poses), and a second thread on a
            shared machine multiplies the time instead of halving it.
        solution_jacobian: False for a fit judged by its solution and residuals alone (a validation refit): no
            Jacobian is evaluated at the solution after the last step; the result then carries no ``normal`` nor
            ``jacobian`` (no covariance) and the rank check at the end uses the last iteration's.

    Returns:
        :class:`LMResult`; it never raises on numerical trouble, the status says what happened.
    """
    if threads is None:
        return _levenberg_marquardt(
            fun, x0, names, max_iter, xtol, ftol, lam0, jacobian, stat_tol, callback, solution_jacobian
        )
    with torch_threads(threads):
        return _levenberg_marquardt(
            fun, x0, names, max_iter, xtol, ftol, lam0, jacobian, stat_tol, callback, solution_jacobian
        )


def _levenberg_marquardt(
    fun, x0, names, max_iter, xtol, ftol, lam0, jacobian, stat_tol, callback, solution_jacobian=True
) -> LMResult:
    jac = jacobian or getattr(fun, "jacobian", None) or torch.func.jacfwd(fun)
    trials = _Trials(fun)
    x = x0.detach().clone()
    r = fun(x).detach()
    cost = 0.5 * float(r.square().sum())
    history = [cost]
    names = list(names or [f"x{i}" for i in range(len(x))])
    if not math.isfinite(cost):
        return LMResult(FitStatus.DIVERGED, 0, x, history, names, len(r), "non-finite residuals at the start")
    lam = lam0
    status, message = FitStatus.MAX_ITERATIONS, f"stopped after {max_iter} iterations"
    it = 0
    eye = torch.eye(len(x), dtype=x.dtype, device=x.device)
    singular = 0  # iterations among the first SINGULAR_WINDOW with a singular normal matrix
    J_at_x = False  # whether J is the Jacobian at the current x (then the solution's needs no new evaluation)
    J = N = None
    for it in range(1, max_iter + 1):
        J = jac(x).detach()
        J_at_x = True
        N = J.T @ J
        s = _jacobi(N)  # Jacobi scaling: solve in y = x / s, where N has a unit diagonal
        Ns = N * s[:, None] * s[None, :]
        gs = (J.T @ r) * s
        if it <= SINGULAR_WINDOW:
            singular += _singular(Ns)
            if it == SINGULAR_WINDOW and singular >= SINGULAR_MIN:
                status, message = (
                    FitStatus.FAILED_SOLVE,
                    f"the normal matrix was singular (rank deficient) in {singular} of the first {SINGULAR_WINDOW} "
                    "iterations",
                )
                it -= 1  # no step taken in this one; J is the Jacobian at x
                break
        # probe a ladder of dampings around the current one (residual evaluations are cheap next to a
        # Jacobian) and keep the lowest cost: in curved valleys of weakly determined parameters a
        # single trial per iteration makes the damping oscillate and the fit creep
        best = _ladder(trials, x, cost, Ns, gs, s, lam)
        while best is None and lam < 1e16:  # nothing lower: damp harder until a step helps
            lam *= 10.0
            best = _attempt(fun, x, cost, Ns, gs, s, lam)
        accepted = best is not None
        if accepted:
            cost_new, lam, dx, r_new = best
            lam = max(lam, 1e-15)
        if not accepted:
            if int(torch.linalg.cholesky_ex(Ns + 1e-12 * eye)[1]) != 0 and cost > 0:
                status, message = FitStatus.FAILED_SOLVE, "the damped normal equations could not be solved"
            else:
                status, message = FitStatus.CONVERGED, "no step lowers the cost any more"
            break
        reduction = (cost - cost_new) / max(cost, 1e-300)
        step_small = bool((dx.abs() <= xtol * (x.abs() + s)).all())
        invisible = (cost - cost_new) < stat_tol * max(1.0, 2.0 * cost / max(len(r) - len(x), 1))
        x, r, cost, J_at_x = x + dx, r_new, cost_new, False
        history.append(cost)
        if callback is not None:
            callback(it, x, cost)
        if step_small or reduction < ftol or invisible:
            status = FitStatus.CONVERGED
            message = (
                "step below xtol"
                if step_small
                else "cost reduction below ftol"
                if reduction < ftol
                else "cost reduction statistically invisible (stat_tol)"
            )
            break
    if not J_at_x and (solution_jacobian or J is None):  # a step was taken after the last Jacobian (or none was)
        J, J_at_x = jac(x).detach(), True
        N = J.T @ J
    return _finish(LMResult(status, it, x, history, names, len(r), message, N, r, J), J_at_x)


def _finish(res: LMResult, at_solution: bool) -> LMResult:
    """``res`` failed where its normal matrix (the solution's, else the last iteration's) is singular; a normal
    matrix and Jacobian not at the solution are dropped from it unless they name that failure."""
    N = res.normal
    s = _jacobi(N)
    if res.status != FitStatus.FAILED_SOLVE and int(torch.linalg.cholesky_ex(N * s[:, None] * s[None, :])[1]) != 0:
        res.status = FitStatus.FAILED_SOLVE
        res.message = "the normal matrix at the solution is singular (rank deficient)"
    if not at_solution and res.status != FitStatus.FAILED_SOLVE:
        res.normal = res.jacobian = None
    return res
