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


class _Probe:
    """The objective along the search direction: ``at(t)`` evaluates it at ``x + t d`` and counts the
    evaluations; ``sufficient(t, f_new)`` and ``curved(gtd_new)`` are the strong Wolfe conditions."""

    def __init__(self, obj_func, x, d, f, gtd, c1: float, c2: float):
        self.obj_func, self.x, self.d, self.f, self.gtd, self.c1, self.c2 = obj_func, x, d, f, gtd, c1, c2
        self.evals = 0

    def at(self, t):
        f_new, g_new = self.obj_func(self.x, t, self.d)
        self.evals += 1
        return f_new, g_new, g_new.dot(self.d)

    def sufficient(self, t, f_new) -> bool:
        return not f_new > (self.f + self.c1 * t * self.gtd)

    def curved(self, gtd_new) -> bool:
        return abs(gtd_new) <= -self.c2 * self.gtd


def _strong_wolfe(obj_func, x, t, d, f, g, gtd, c1=1e-4, c2=0.9, tolerance_change=1e-9, max_ls=25):
    """A step ``t`` along ``d`` from ``x`` that satisfies the strong Wolfe conditions (sufficient decrease ``c1``,
    curvature ``c2``), or the best point found in ``max_ls`` evaluations: ``(f, g, t, evaluations)``."""
    probe = _Probe(obj_func, x, d, f, gtd, c1, c2)
    g = g.clone(memory_format=torch.contiguous_format)
    bracket, done, ls_iter = _bracket(probe, t, g, max_ls)
    low_pos = _zoom(probe, bracket, done, ls_iter, max_ls, d.abs().max(), tolerance_change)
    return bracket[1][low_pos], bracket[2][low_pos], bracket[0][low_pos], probe.evals


def _bracket(probe: _Probe, t, g, max_ls: int):
    """Bracket an interval that holds a point satisfying the conditions, extrapolating by cubic interpolation.
    Returns ``([steps, values, gradients, slopes], done, iterations)``; ``done``: the bracket's one step already
    satisfies them."""
    f, gtd = probe.f, probe.gtd
    f_new, g_new, gtd_new = probe.at(t)
    t_prev, f_prev, g_prev, gtd_prev = 0, f, g, gtd
    ls_iter = 0
    while ls_iter < max_ls:
        passed = not probe.sufficient(t, f_new) or (ls_iter > 1 and f_new >= f_prev)
        if not passed and probe.curved(gtd_new):
            return [[t], [f_new], [g_new], [gtd_new]], True, ls_iter
        if passed or gtd_new >= 0:  # beyond a minimum: it lies between the last two steps
            g_new = g_new.clone(memory_format=torch.contiguous_format)
            return [[t_prev, t], [f_prev, f_new], [g_prev, g_new], [gtd_prev, gtd_new]], False, ls_iter
        # extrapolate by cubic interpolation, at least 1 % beyond t and at most 10 t
        min_step = t + 0.01 * (t - t_prev)
        max_step = t * 10
        tmp = t
        t = _cubic_interpolate(t_prev, f_prev, gtd_prev, t, f_new, gtd_new, bounds=(min_step, max_step))
        t_prev = tmp
        f_prev = f_new
        g_prev = g_new.clone(memory_format=torch.contiguous_format)
        gtd_prev = gtd_new
        f_new, g_new, gtd_new = probe.at(t)
        ls_iter += 1
    # no bracket in max_ls evaluations: the zoom does not run, the better end is returned
    return [[0, t], [f, f_new], [g, g_new], [None, None]], False, ls_iter


def _zoom(probe: _Probe, bracket, done: bool, ls_iter: int, max_ls: int, d_norm, tolerance_change: float) -> int:
    """Shrink ``bracket`` (edited in place) until a point satisfies the conditions; returns its low end's index."""
    steps, values, grads, slopes = bracket
    insuf_progress = False
    low_pos, high_pos = (0, 1) if values[0] <= values[-1] else (1, 0)
    while not done and ls_iter < max_ls:
        if abs(steps[1] - steps[0]) * d_norm < tolerance_change:
            break
        t = _cubic_interpolate(steps[0], values[0], slopes[0], steps[1], values[1], slopes[1])
        t, insuf_progress = _away_from_ends(t, steps, insuf_progress)
        f_new, g_new, gtd_new = probe.at(t)
        ls_iter += 1
        if not probe.sufficient(t, f_new) or f_new >= values[low_pos]:
            # no sufficient decrease, or not below the low end: the new high end
            steps[high_pos], values[high_pos], slopes[high_pos] = t, f_new, gtd_new
            grads[high_pos] = g_new.clone(memory_format=torch.contiguous_format)
            low_pos, high_pos = (0, 1) if values[0] <= values[1] else (1, 0)
            continue
        if probe.curved(gtd_new):
            done = True
        elif gtd_new * (steps[high_pos] - steps[low_pos]) >= 0:
            # the old low end becomes the high end
            for part in bracket:
                part[high_pos] = part[low_pos]
        steps[low_pos], values[low_pos], slopes[low_pos] = t, f_new, gtd_new
        grads[low_pos] = g_new.clone(memory_format=torch.contiguous_format)
    return low_pos


def _away_from_ends(t, steps, insuf_progress: bool):
    """A trial within a tenth of the bracket from its ends counts as insufficient progress; twice in a row (or at
    an end) it moves to a tenth of the bracket from the nearer end. Returns the trial and the flag."""
    eps = 0.1 * (max(steps) - min(steps))
    if min(max(steps) - t, t - min(steps)) >= eps:
        return t, False
    if not (insuf_progress or t >= max(steps) or t <= min(steps)):
        return t, True
    t = max(steps) - eps if abs(t - max(steps)) < abs(t - min(steps)) else min(steps) + eps
    return t, False


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
