"""Constants inside forward-mode differentiation (``torch.func.jvp`` and ``jacfwd``), kept off torch's Python path.

Inside a forward-mode pass, an elementwise add, sub, mul or div between a tensor that carries a tangent and an
operand that does not (a plain tensor, or a Python number as in ``x * 2.0`` or ``x / 6.0``) gives the plain operand
an efficient zero tangent, and torch's kernels for arithmetic on such zero tensors work out the output's shape
through the operator's Python reference (``torch._refs``, through the meta registrations), whose wrapper imports
``torch._dynamo`` (with sympy, ``torch.distributed`` and ``torch.onnx``: hundreds of modules) at its first call and
then runs a few hundred Python calls per operation. A calibration's Jacobians are forward-mode passes over models
whose constants (the nominal pose, joint readings, gravity torques, a drift's time) meet the parameters this way.

The helpers compute the same values without that path:

* :func:`mul_scalar`, :func:`div_scalar` and :func:`add_scalar` (a tensor times, over or plus a Python number) call
  the operator's overload for a number (``torch.ops.aten.mul.Scalar``), whose tangent rule takes the number as a
  constant. ``x * c`` with a Python number runs that overload's kernel too (the number wrapped as a tensor), so the
  values and the tangents are the same bits;
* :func:`lift` and :func:`lift_pair` give a plain tensor that meets a differentiated one an explicit zero tangent
  (a select, ``torch.where``, which forward mode differentiates in C++), so that the operation between them sees
  two tangents. The values are the same bits; a tangent gains ``+ 0`` (or ``0 *`` a value) where it had a copy,
  which changes nothing but, at most, the sign of a tangent that is exactly zero.

Outside forward mode :func:`lift` returns its argument unchanged (one look-up of the tensor's tangent), so
plain evaluations, the residuals of every least-squares iteration, cost what they did.
"""

from __future__ import annotations

import torch
from torch.autograd import forward_ad

Tensor = torch.Tensor

_mul = torch.ops.aten.mul.Scalar
_div = torch.ops.aten.div.Scalar
_add = torch.ops.aten.add.Scalar


def mul_scalar(x: Tensor, c: float) -> Tensor:
    """``x * c`` for a Python number ``c`` (any shape), with ``c`` a constant of forward mode (module docstring)."""
    return _mul(x, c)


def div_scalar(x: Tensor, c: float) -> Tensor:
    """``x / c`` for a Python number ``c`` (any shape), with ``c`` a constant of forward mode (module docstring)."""
    return _div(x, c)


def add_scalar(x: Tensor, c: float) -> Tensor:
    """``x + c`` for a Python number ``c`` (any shape), with ``c`` a constant of forward mode (module docstring)."""
    return _add(x, c)


def has_tangent(x: Tensor) -> bool:
    """Whether ``x`` carries a tangent of the innermost forward-mode level (``torch.func.jvp`` / ``jacfwd`` and
    ``torch.autograd.forward_ad`` alike); False outside forward mode. A tensor derived from a differentiated one
    without a derivative (``zeros_like``, ``detach``) has none."""
    return forward_ad.unpack_dual(x).tangent is not None


def lift(c: Tensor, like: Tensor) -> Tensor:
    """``c`` with a zero tangent where ``like`` carries a forward-mode tangent and ``c`` does not.

    Args:
        c: the constant, any shape broadcastable with ``like``.
        like: the tensor ``c`` is about to meet in an elementwise operation.

    Returns:
        ``c`` itself outside forward mode (or when ``c`` has a tangent, or ``like`` none); else the same values
        broadcast to the shape of ``c`` and ``like`` together, with a zero tangent.
    """
    if not has_tangent(like) or has_tangent(c):
        return c
    return torch.where(torch.ones((), dtype=torch.bool, device=c.device), c, like)


def lift_pair(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """``a, b`` for an elementwise operation between them: the one without a forward-mode tangent :func:`lift`-ed
    when the other has one; both unchanged otherwise."""
    ta, tb = has_tangent(a), has_tangent(b)
    if ta == tb:
        return a, b
    true = torch.ones((), dtype=torch.bool, device=a.device)
    return (a, torch.where(true, b, a)) if ta else (torch.where(true, a, b), b)
