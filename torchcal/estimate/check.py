"""A public Jacobian checker: any analytic or autograd Jacobian against central finite differences."""

from __future__ import annotations

from collections.abc import Callable

import torch

Tensor = torch.Tensor


def finite_difference_jacobian(fun: Callable[[Tensor], Tensor], x: Tensor, eps: float = 1e-6) -> Tensor:
    """Central differences ``(f(x + e_k h) - f(x - e_k h)) / 2h`` per coordinate: ``(*f.shape, x.numel())``."""
    x = x.detach()
    cols = []
    for k in range(x.numel()):
        dx = torch.zeros_like(x).flatten()
        dx[k] = eps
        dx = dx.reshape(x.shape)
        cols.append((fun(x + dx) - fun(x - dx)) / (2 * eps))
    return torch.stack(cols, dim=-1)


def check_jacobian(fun: Callable[[Tensor], Tensor], x: Tensor, J: Tensor, eps: float = 1e-6) -> float:
    """Largest difference between ``J`` and central finite differences, relative to the largest entry of ``J``."""
    fd = finite_difference_jacobian(fun, x, eps).reshape(J.shape)
    return float((fd - J).abs().max() / J.abs().max().clamp(min=1e-300))
