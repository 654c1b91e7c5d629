"""The private torch internals torchcal relies on, each behind one small function with a fallback.

torch has no public API for any of the three; each function says why torchcal needs it, what public API would
replace it, and what it does in a torch that lacks the private attribute: there the callers compute more and
keep less, and their results are the same. No other module of torchcal names these internals
(``tests/test_private_torch.py``).

* :func:`plain`: whether a tensor is an ordinary one, not a ``torch.func`` transform's wrapper;
* :func:`version_key` and :func:`same_version`: a cache key from tensors' in-place version counters;
* :func:`backward`: a reverse pass handed straight to the autograd engine.
"""

from __future__ import annotations

import torch

Tensor = torch.Tensor

#: ``torch._C._functorch.is_functorch_wrapped_tensor``, or None where this torch has no such function
_IS_WRAPPED = getattr(getattr(torch._C, "_functorch", None), "is_functorch_wrapped_tensor", None)
#: the autograd engine behind ``torch.autograd.backward``, or None where this torch does not expose it
_ENGINE = getattr(getattr(torch.autograd, "Variable", None), "_execution_engine", None)


def plain(t: Tensor) -> bool:
    """Whether ``t`` is known to be an ordinary tensor: not the wrapper that a ``torch.func`` transform (``vmap``,
    ``grad``, ``jacrev``, ``jvp``) passes through the code it transforms.

    Why: code that keeps its last result for the same inputs (see :func:`version_key`) must not keep one computed
    from a wrapper, which belongs to one transform level and is an error outside it; ``requires_grad`` does not
    tell (under ``vmap`` or ``jvp`` a wrapper need not require a gradient).

    Public replacement: none in torch 2.x; ``torch.func`` itself uses
    ``torch._C._functorch.is_functorch_wrapped_tensor``. A public predicate would replace it.

    Fallback: where this torch lacks that function no tensor is known to be plain (False), so the callers keep
    nothing and compute every time.
    """
    return _IS_WRAPPED is not None and not _IS_WRAPPED(t)


def version_key(*tensors: Tensor | None) -> tuple | None:
    """A key naming ``tensors`` (``None`` entries skipped) as they are now: each tensor object with its in-place
    version counter; ``None`` where they cannot be keyed.

    Why: a least-squares fit evaluates the same effect at the same joint-angle tensor many times, and a result
    kept under this key is reused while its inputs are the same objects, unmodified in place (every in-place
    operation bumps the counter), so the reused result is the one a new computation would give. The key holds
    the tensors themselves, so no other tensor can take an object's place while the key lives.

    Public replacement: none; ``Tensor._version`` is the counter autograd checks its saved tensors against.

    Fallback: ``None`` where a tensor is not :func:`plain` or has no version counter (a torch without
    ``_version``): the caller then keeps nothing.
    """
    key = []
    for t in tensors:
        if t is None:
            continue
        version = getattr(t, "_version", None)
        if version is None or not plain(t):
            return None
        key.append((t, version))
    return tuple(key)


def same_version(a: tuple | None, b: tuple | None) -> bool:
    """Whether two keys of :func:`version_key` name the same tensor objects at the same versions (never where
    either is ``None``)."""
    return (
        a is not None and b is not None and len(a) == len(b) and all(x is y and u == v for (x, u), (y, v) in zip(a, b))
    )


def backward(out: Tensor, cotangent: Tensor, retain: bool) -> None:
    """``out.backward(cotangent, retain_graph=retain)``: the product of ``cotangent`` with the Jacobian of ``out``,
    accumulated into the ``.grad`` of the leaves that ``out`` depends on.

    Why: the filter's autodiff Jacobian runs three small backward passes per Kalman step, and the public
    wrapper's argument handling (gradient checks, tuple conversions) costs about as much as one such pass; the
    engine call skips it and gives the same gradients.

    Public replacement: ``torch.autograd.backward`` itself, should its per-call overhead shrink.

    Fallback: ``torch.autograd.backward`` where this torch has no ``Variable._execution_engine``.
    """
    if _ENGINE is None:
        torch.autograd.backward(out, cotangent, retain_graph=retain)
    else:
        # (tensors, grad_tensors, keep_graph, create_graph, inputs, allow_unreachable, accumulate_grad)
        _ENGINE.run_backward((out,), (cotangent,), retain, False, (), True, True)
