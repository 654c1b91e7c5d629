"""L-BFGS with a strong-Wolfe line search over one leaf tensor, without ``torch.optim``.

Constructing any ``torch.optim`` optimizer (and its ``zero_grad``) goes through wrappers that import
``torch._dynamo`` (with sympy, ``torch.distributed`` and ``torch.onnx``: hundreds of modules) at their first call; a
calibration fits a few hyperparameters with L-BFGS and needs none of that. :func:`minimize` is the algorithm of
``torch.optim.LBFGS(params=[theta], lr, max_iter, max_eval, tolerance_grad, tolerance_change, history_size,
line_search_fn="strong_wolfe")`` stepped once with a closure: the same operations in the same order on the same
types (Python floats and 0-dim tensors where torch has them), so it evaluates the closure at the same points and
ends at the same bits.

The algorithm and its structure follow PyTorch's ``torch/optim/lbfgs.py`` (BSD-3-Clause, Copyright (c) 2016-
Facebook, Inc. and the PyTorch contributors), itself a port of ``optim/lbfgs.lua`` and ``optim/lswolfe.lua`` of
Torch7 and inspired by minFunc (Mark Schmidt): two-loop recursion over the last ``history_size`` pairs, the first
step scaled to ``min(1, 1 / |g|_1)``, and a bracketing then zooming line search with cubic interpolation (Nocedal &
Wright, Numerical Optimization, 2nd ed., algorithms 3.5 and 3.6).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

Tensor = torch.Tensor


def _cubic_interpolate(x1, f1, g1, x2, f2, g2, bounds=None):
    """The minimiser of the cubic through ``(x1, f1, g1)`` and ``(x2, f2, g2)`` clipped to ``bounds`` (default the
    interval between the points); the middle of the bounds when the cubic has no minimiser."""
    if bounds is not None:
        xmin_bound, xmax_bound = bounds
    else:
        xmin_bound, xmax_bound = (x1, x2) if x1 <= x2 else (x2, x1)
    d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
    d2_square = d1**2 - g1 * g2
    if d2_square >= 0:
        d2 = d2_square.sqrt()
        if x1 <= x2:
            min_pos = x2 - (x2 - x1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
        else:
            min_pos = x1 - (x1 - x2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
        return min(max(min_pos, xmin_bound), xmax_bound)
    return (xmin_bound + xmax_bound) / 2.0


def _strong_wolfe(obj_func, x, t, d, f, g, gtd, c1=1e-4, c2=0.9, tolerance_change=1e-9, max_ls=25):
    """A step ``t`` along ``d`` from ``x`` that satisfies the strong Wolfe conditions (sufficient decrease ``c1``,
    curvature ``c2``), or the best point found in ``max_ls`` evaluations: ``(f, g, t, evaluations)``."""
    d_norm = d.abs().max()
    g = g.clone(memory_format=torch.contiguous_format)
    f_new, g_new = obj_func(x, t, d)
    ls_func_evals = 1
    gtd_new = g_new.dot(d)

    # bracket an interval containing a point that satisfies the conditions
    t_prev, f_prev, g_prev, gtd_prev = 0, f, g, gtd
    done = False
    ls_iter = 0
    while ls_iter < max_ls:
        if f_new > (f + c1 * t * gtd) or (ls_iter > 1 and f_new >= f_prev):
            bracket = [t_prev, t]
            bracket_f = [f_prev, f_new]
            bracket_g = [g_prev, g_new.clone(memory_format=torch.contiguous_format)]
            bracket_gtd = [gtd_prev, gtd_new]
            break
        if abs(gtd_new) <= -c2 * gtd:
            bracket, bracket_f, bracket_g = [t], [f_new], [g_new]
            done = True
            break
        if gtd_new >= 0:
            bracket = [t_prev, t]
            bracket_f = [f_prev, f_new]
            bracket_g = [g_prev, g_new.clone(memory_format=torch.contiguous_format)]
            bracket_gtd = [gtd_prev, gtd_new]
            break
        # extrapolate by cubic interpolation, at least 1 % beyond t and at most 10 t
        min_step = t + 0.01 * (t - t_prev)
        max_step = t * 10
        tmp = t
        t = _cubic_interpolate(t_prev, f_prev, gtd_prev, t, f_new, gtd_new, bounds=(min_step, max_step))
        t_prev = tmp
        f_prev = f_new
        g_prev = g_new.clone(memory_format=torch.contiguous_format)
        gtd_prev = gtd_new
        f_new, g_new = obj_func(x, t, d)
        ls_func_evals += 1
        gtd_new = g_new.dot(d)
        ls_iter += 1

    if ls_iter == max_ls:
        bracket = [0, t]
        bracket_f = [f, f_new]
        bracket_g = [g, g_new]

    # zoom: shrink the bracket until a point satisfies the conditions
    insuf_progress = False
    low_pos, high_pos = (0, 1) if bracket_f[0] <= bracket_f[-1] else (1, 0)
    while not done and ls_iter < max_ls:
        if abs(bracket[1] - bracket[0]) * d_norm < tolerance_change:
            break
        t = _cubic_interpolate(bracket[0], bracket_f[0], bracket_gtd[0], bracket[1], bracket_f[1], bracket_gtd[1])
        # a trial within a tenth of the bracket from its ends counts as insufficient progress; twice in a row (or at
        # an end) it moves to a tenth of the bracket from the nearer end
        eps = 0.1 * (max(bracket) - min(bracket))
        if min(max(bracket) - t, t - min(bracket)) < eps:
            if insuf_progress or t >= max(bracket) or t <= min(bracket):
                if abs(t - max(bracket)) < abs(t - min(bracket)):
                    t = max(bracket) - eps
                else:
                    t = min(bracket) + eps
                insuf_progress = False
            else:
                insuf_progress = True
        else:
            insuf_progress = False
        f_new, g_new = obj_func(x, t, d)
        ls_func_evals += 1
        gtd_new = g_new.dot(d)
        ls_iter += 1
        if f_new > (f + c1 * t * gtd) or f_new >= bracket_f[low_pos]:
            # no sufficient decrease, or not below the low end: the new high end
            bracket[high_pos] = t
            bracket_f[high_pos] = f_new
            bracket_g[high_pos] = g_new.clone(memory_format=torch.contiguous_format)
            bracket_gtd[high_pos] = gtd_new
            low_pos, high_pos = (0, 1) if bracket_f[0] <= bracket_f[1] else (1, 0)
        else:
            if abs(gtd_new) <= -c2 * gtd:
                done = True
            elif gtd_new * (bracket[high_pos] - bracket[low_pos]) >= 0:
                # the old low end becomes the high end
                bracket[high_pos] = bracket[low_pos]
                bracket_f[high_pos] = bracket_f[low_pos]
                bracket_g[high_pos] = bracket_g[low_pos]
                bracket_gtd[high_pos] = bracket_gtd[low_pos]
            bracket[low_pos] = t
            bracket_f[low_pos] = f_new
            bracket_g[low_pos] = g_new.clone(memory_format=torch.contiguous_format)
            bracket_gtd[low_pos] = gtd_new

    return bracket_f[low_pos], bracket_g[low_pos], bracket[low_pos], ls_func_evals


def minimize(
    closure: Callable[[], Tensor | float],
    theta: Tensor,
    *,
    max_iter: int = 20,
    max_eval: int | None = None,
    lr: float = 1.0,
    tolerance_grad: float = 1e-7,
    tolerance_change: float = 1e-9,
    history_size: int = 100,
) -> float:
    """Minimise ``closure()`` over the leaf ``theta`` in place, as one ``torch.optim.LBFGS(...).step(closure)`` with
    ``line_search_fn="strong_wolfe"`` and the same arguments (module docstring).

    Args:
        closure: evaluates the loss at ``theta``'s current value and leaves its gradient in ``theta.grad`` (set it,
            or clear it and call ``loss.backward()``), as a ``torch.optim`` closure does; returns the loss (a 0-dim
            tensor or a float). It runs with gradients enabled; the rest of the method without.
        theta: the parameters, a floating tensor of any shape (updated in place).
        max_iter: the most iterations.
        max_eval: the most evaluations of ``closure`` (default ``max_iter * 5 // 4``).
        lr: the first trial step of every iteration after the first (the first is ``min(1, 1 / |g|_1) * lr``).
        tolerance_grad: stop when the largest gradient element is at most this.
        tolerance_change: stop when the step or the loss changes by less than this.
        history_size: the number of curvature pairs kept.

    Returns:
        The loss at the starting point, as a float.
    """
    if max_eval is None:
        max_eval = max_iter * 5 // 4

    def evaluate() -> float:
        with torch.enable_grad():
            loss = closure()
        return float(loss)

    def flat_grad_now() -> Tensor:
        # a fresh flat copy of theta.grad (zeros when the closure left none), as torch.optim gathers it
        if theta.grad is None:
            return theta.new(theta.numel()).zero_()
        return torch.cat([theta.grad.view(-1)], 0)

    with torch.no_grad():
        return _run(
            evaluate, flat_grad_now, theta, max_iter, max_eval, lr, tolerance_grad, tolerance_change, history_size
        )


def _run(evaluate, flat_grad_now, theta, max_iter, max_eval, lr, tolerance_grad, tolerance_change, history_size):
    def add_step(t, d):
        theta.add_(d.view_as(theta), alpha=t)

    def directional_evaluate(x, t, d):
        add_step(t, d)
        loss = evaluate()
        flat_grad = flat_grad_now()
        theta.copy_(x)
        return loss, flat_grad

    loss = evaluate()
    orig_loss = loss
    current_evals = 1
    flat_grad = flat_grad_now()
    if flat_grad.abs().max() <= tolerance_grad:
        return orig_loss

    d = t = prev_flat_grad = None
    old_dirs: list[Tensor] = []
    old_stps: list[Tensor] = []
    ro: list = []
    al: list = [None] * history_size
    H_diag = 1
    n_iter = 0
    while n_iter < max_iter:
        n_iter += 1
        # the direction: steepest descent first, then the two-loop recursion over the stored pairs
        if n_iter == 1:
            d = flat_grad.neg()
        else:
            y = flat_grad.sub(prev_flat_grad)
            s = d.mul(t)
            ys = y.dot(s)
            if ys > 1e-10:  # keep only pairs of positive curvature
                if len(old_dirs) == history_size:
                    old_dirs.pop(0)
                    old_stps.pop(0)
                    ro.pop(0)
                old_dirs.append(y)
                old_stps.append(s)
                ro.append(1.0 / ys)
                H_diag = ys / y.dot(y)
            num_old = len(old_dirs)
            q = flat_grad.neg()
            for i in range(num_old - 1, -1, -1):
                al[i] = old_stps[i].dot(q) * ro[i]
                q.add_(old_dirs[i], alpha=-al[i])
            d = r = torch.mul(q, H_diag)
            for i in range(num_old):
                be_i = old_dirs[i].dot(r) * ro[i]
                r.add_(old_stps[i], alpha=al[i] - be_i)

        if prev_flat_grad is None:
            prev_flat_grad = flat_grad.clone(memory_format=torch.contiguous_format)
        else:
            prev_flat_grad.copy_(flat_grad)
        prev_loss = loss

        t = min(1.0, 1.0 / flat_grad.abs().sum()) * lr if n_iter == 1 else lr
        gtd = flat_grad.dot(d)
        if gtd > -tolerance_change:  # not a descent direction
            break

        x_init = theta.clone(memory_format=torch.contiguous_format)
        loss, flat_grad, t, ls_func_evals = _strong_wolfe(
            directional_evaluate, x_init, t, d, loss, flat_grad, gtd, max_ls=max_eval - current_evals
        )
        add_step(t, d)
        current_evals += ls_func_evals

        if n_iter == max_iter or current_evals >= max_eval:
            break
        if flat_grad.abs().max() <= tolerance_grad:
            break
        if d.mul(t).abs().max() <= tolerance_change:
            break
        if abs(loss - prev_loss) < tolerance_change:
            break
    return orig_loss
