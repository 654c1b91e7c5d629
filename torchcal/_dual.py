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
* :func:`add`, :func:`sub`, :func:`mul` and :func:`div` of two tensors give the operand without a tangent, when the
  other has one, a zero tangent of its own (``forward_ad.make_dual``; for a sum, a broadcast zero that takes no
  memory), so that the operation meets two tangents in C++. The values are the same bits, and so are the tangents:
  each zero is signed so that the term it makes in the tangent rule is ``-0.0`` where it is added and ``+0.0``
  where it is subtracted (``t + -0.0`` is ``t`` for every ``t``, ``-0.0`` included), which leaves torch's tangent
  as it is (but where a value is infinite or not a number, or a divisor zero).

Outside forward mode they are the plain operations after one look-up of each operand's tangent, so plain
evaluations, the residuals of every least-squares iteration, cost what they did.
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


def _lift(c: Tensor, zero: float | Tensor) -> Tensor:
    """``c`` with the tangent ``zero``: ``0.0`` or ``-0.0`` everywhere (broadcast from one element), or a tensor of
    signed zeros of ``c``'s shape."""
    if not isinstance(zero, Tensor):
        zero = torch.full((), zero, dtype=c.dtype, device=c.device).expand(c.shape)
    return forward_ad.make_dual(c, zero)


def _pair(a: Tensor, b: Tensor, zero_a: float, zero_b: float) -> tuple[Tensor, Tensor]:
    ta, tb = has_tangent(a), has_tangent(b)
    if ta == tb:
        return a, b
    return (a, _lift(b, zero_b)) if ta else (_lift(a, zero_a), b)


def add(a: Tensor, b: Tensor) -> Tensor:
    """``a + b`` (broadcast), either one a constant of forward mode (module docstring)."""
    # the tangent t + (-0.0) is t for every t
    return torch.add(*_pair(a, b, -0.0, -0.0))


def sub(a: Tensor, b: Tensor) -> Tensor:
    """``a - b`` (broadcast), either one a constant of forward mode (module docstring)."""
    # t - (+0.0) is t and (-0.0) - t is -t for every t
    return torch.sub(*_pair(a, b, -0.0, 0.0))


def mul(a: Tensor, b: Tensor) -> Tensor:
    """``a * b`` (broadcast), either one a constant of forward mode (module docstring)."""
    ta, tb = has_tangent(a), has_tangent(b)
    if ta == tb:
        return torch.mul(a, b)
    # the tangent is z * x + x_t * c (x the differentiated factor's value, c the constant): with z = -0.0 * x, the
    # product z * x is -0.0 whatever the sign of x, and x_t * c + (-0.0) is x_t * c, torch's tangent to the bit
    x, c = _broadcast(forward_ad.unpack_dual(a if ta else b).primal, b if ta else a)
    c = _lift(c, x * -0.0)
    return torch.mul(a, c) if ta else torch.mul(c, b)


def div(a: Tensor, b: Tensor) -> Tensor:
    """``a / b`` (broadcast), either one a constant of forward mode (module docstring)."""
    ta, tb = has_tangent(a), has_tangent(b)
    if ta == tb:
        return torch.div(a, b)
    if tb:  # constant / x: the tangent (z - x_t * r) / x with z = -0.0 is -(x_t * r) / x, torch's to the bit
        return torch.div(_lift(a, -0.0), b)
    # x / constant: the tangent (x_t - z * r) / c with r = x / c; z = 0.0 * r makes z * r +0.0, and x_t - (+0.0) is x_t
    x, c = _broadcast(forward_ad.unpack_dual(a).primal, b)
    return torch.div(a, _lift(c, torch.div(x, c) * 0.0))


def _broadcast(x: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """``x`` and ``c`` broadcast together, ``c`` copied where it grew (a dual's value cannot be a broadcast view)."""
    x, cb = torch.broadcast_tensors(x, c)
    return x, (c if cb.shape == c.shape else cb.contiguous())
