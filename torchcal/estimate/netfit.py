"""Fitting a :class:`CorrectionNet` to position corrections: Levenberg-Marquardt or LBFGS.

The network is small (the paper's 6-29-3 has 293 weights), so LM with the full Jacobian
(``torch.func.jacrev`` of the per-sample outputs, vectorised with ``vmap``) is affordable and
converges in tens of iterations where gradient methods need thousands. A held-out
validation share stops the fit at its best validation error (early stopping), and a small
ridge term keeps the weights from running off where the data say nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal.effects.learned import CorrectionNet
from torchcal.estimate.lm import FitStatus

Tensor = torch.Tensor


@dataclass
class NetFitResult:
    status: FitStatus
    iterations: int
    train_rmse: list[float] = field(default_factory=list)  # m, per iteration
    val_rmse: list[float] = field(default_factory=list)  # m, per iteration (empty without validation)
    best_iteration: int = 0
    method: str = "lm"


def _flat(net: CorrectionNet) -> Tensor:
    return torch.nn.utils.parameters_to_vector(net.parameters()).detach().clone()


def _unflat(net: CorrectionNet, w: Tensor) -> dict[str, Tensor]:
    out, k = {}, 0
    for name, p in net.named_parameters():
        out[name] = w[k : k + p.numel()].reshape(p.shape)
        k += p.numel()
    return out


def net_forward(net: CorrectionNet, w: Tensor, q: Tensor) -> Tensor:
    """The network's output ``(N, 3)`` with flat weights ``w`` (functional, differentiable in ``w``)."""
    return torch.func.functional_call(net, _unflat(net, w), (q,))


def net_jacobian(net: CorrectionNet, w: Tensor, q: Tensor) -> Tensor:
    """Per-sample Jacobians ``d net(q_i) / dw`` ``(N, 3, n_weights)``, analytic (``CorrectionNet.jacobian_flat``)."""
    return net.jacobian_flat(w, q)[1]


def _rmse(e: Tensor) -> float:
    return float(e.reshape(-1, 3).norm(dim=-1).square().mean().sqrt())


def fit_net(
    net: CorrectionNet,
    q: Tensor,
    target: Tensor,
    *,
    val: tuple[Tensor, Tensor] | None = None,
    method: str = "lm",
    iterations: int = 100,
    ridge: float = 1e-6,
    patience: int = 15,
    generator: torch.Generator | None = None,
    ftol: float = 1e-10,
) -> NetFitResult:
    """Fit ``net(q) ~ target`` [m] in place; keep the weights of the best validation error.

    Args:
        q: ``(N, dof)`` inputs; target: ``(N, 3)`` corrections [m].
        val: optional ``(q_val, target_val)`` for early stopping.
        method: "lm" or "lbfgs".
        iterations: LM iterations or LBFGS outer steps.
        ridge: weight of ``|w|^2`` relative to the squared residuals in mm^2.
        patience: stop after this many iterations without a better validation error.
        ftol: stop when an LM step lowers the cost by less than this fraction (warm-started refits
            converge in a few iterations with ftol ~ 1e-6).
    """
    if method not in ("lm", "lbfgs"):
        from torchcal.errors import OptionError

        raise OptionError(f"network fit method '{method}' is not one of ['lm', 'lbfgs']")
    w = _flat(net)
    scale = 1e3  # residuals in mm: well scaled for the damping and the ridge

    def residual(wv):
        r = (net_forward(net, wv, q) - target).reshape(-1) * scale
        return torch.cat([r, math.sqrt(ridge) * wv])

    def val_rmse(wv):
        with torch.no_grad():
            return _rmse(net_forward(net, wv, val[0]) - val[1]) if val is not None else float("nan")

    res = NetFitResult(FitStatus.MAX_ITERATIONS, 0, method=method)
    best_w, best_val = w.clone(), val_rmse(w)
    res.val_rmse.append(best_val)
    with torch.no_grad():
        res.train_rmse.append(_rmse(net_forward(net, w, q) - target))
    if method == "lbfgs":
        res = _fit_lbfgs(net, w, residual, val_rmse, iterations, patience, res)
        best_w = w  # _fit_lbfgs leaves its best weights in w
    else:
        problem = _NetProblem(net, q, target, residual, val_rmse, ridge, scale, has_val=val is not None)
        best_w = _fit_lm(problem, w, best_w, best_val, res, iterations=iterations, patience=patience, ftol=ftol)
    torch.nn.utils.vector_to_parameters(best_w, net.parameters())
    return res


@dataclass
class _NetProblem:
    """What the LM iterations of :func:`fit_net` need: the network and its data, the residual (in mm, with the
    ridge rows) and the validation RMSE of a weight vector."""

    net: CorrectionNet
    q: Tensor
    target: Tensor
    residual: object  # weights -> stacked residual (mm, then the ridge rows)
    val_rmse: object  # weights -> validation RMSE [m] (nan without validation poses)
    ridge: float
    scale: float
    has_val: bool


def _lm_step(p: _NetProblem, w: Tensor, r: Tensor, cost: float, lam: float):
    """One LM step from ``w``: the damping raised until the cost falls. Returns ``(w, r, cost, lam)`` of the step
    taken, or None where no damping below 1e12 lowers the cost."""
    n_w = len(w)
    Jnet = net_jacobian(p.net, w, p.q).reshape(-1, n_w) * p.scale
    # the ridge rows sqrt(ridge) * w enter the normal equations directly (no stacked Jacobian)
    g = Jnet.T @ r[:-n_w] + p.ridge * w
    N = Jnet.T @ Jnet
    N.diagonal().add_(p.ridge)
    d = N.diagonal().clamp(min=1e-12)
    while lam < 1e12:
        L, info = torch.linalg.cholesky_ex(N + lam * torch.diag(d))
        if int(info) != 0:
            lam *= 10
            continue
        w_new = w - torch.cholesky_solve(g[:, None], L)[:, 0]
        r_new = p.residual(w_new).detach()
        c_new = float(r_new.square().sum())
        if math.isfinite(c_new) and c_new < cost:
            return w_new, r_new, c_new, lam
        lam *= 10
    return None


def _fit_lm(
    p: _NetProblem, w: Tensor, best_w: Tensor, best_val: float, res, *, iterations: int, patience: int, ftol: float
) -> Tensor:
    """Levenberg-Marquardt on the network's weights from ``w``, with early stopping on the validation error;
    ``res`` records the history. Returns the weights to keep (the best on validation, else the last)."""
    lam = 1e-2
    r = p.residual(w).detach()
    cost = float(r.square().sum())
    since_best = 0
    for it in range(1, iterations + 1):
        step = _lm_step(p, w, r, cost, lam)
        res.iterations = it
        if step is None:
            res.status = FitStatus.CONVERGED
            break
        w_new, r, c_new, lam = step
        rel = (cost - c_new) / max(cost, 1e-300)
        w, cost = w_new, c_new
        lam = max(lam / 10, 1e-9)
        with torch.no_grad():
            res.train_rmse.append(_rmse(net_forward(p.net, w, p.q) - p.target))
        v = p.val_rmse(w)
        res.val_rmse.append(v)
        if not p.has_val or v < best_val:
            best_w, best_val, res.best_iteration, since_best = w.clone(), v, it, 0
        else:
            since_best += 1
        if rel < ftol or (p.has_val and since_best >= patience):
            res.status = FitStatus.CONVERGED
            break
    return w if not p.has_val else best_w


def _fit_lbfgs(net, w, residual, val_rmse, iterations, patience, res):
    wv = w.clone().requires_grad_(True)
    opt = torch.optim.LBFGS(
        [wv],
        lr=1.0,
        max_iter=20,
        history_size=50,
        line_search_fn="strong_wolfe",
        tolerance_grad=1e-12,
        tolerance_change=1e-15,
    )

    def closure():
        opt.zero_grad()
        loss = residual(wv).square().sum()
        loss.backward()
        return loss

    best_w, best_val, since = w.clone(), res.val_rmse[0], 0
    for it in range(1, iterations + 1):
        opt.step(closure)
        res.iterations = it
        v = val_rmse(wv.detach())
        res.val_rmse.append(v)
        if math.isnan(v) or v < best_val:
            best_w, best_val, res.best_iteration, since = wv.detach().clone(), v, it, 0
        else:
            since += 1
            if since >= patience:
                res.status = FitStatus.CONVERGED
                break
    if math.isnan(res.val_rmse[0]):
        best_w = wv.detach().clone()
    w.copy_(best_w)
    return res
