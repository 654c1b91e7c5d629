"""A second device without a GPU, for device-cleanliness tests: CPU tensors that say they live elsewhere.

A :class:`Virtual` tensor wraps a CPU tensor (real values, so ``.item()``, ``float()``, linear algebra and the
whole calibration run) but reports ``device="meta"``. Inside :func:`virtual_device`:

* a factory given ``device=<that device>`` (``torch.zeros(..., device=q.device)``, ``torch.tensor(..., device=...)``,
  ``module.to(q.device)``, ``x.to(q.device)``) builds its values on the CPU and wraps them;
* an operation that meets a ``Virtual`` tensor and a plain CPU tensor with at least one dimension raises, as CUDA
  does: a constructor that forgot its device is caught where it first meets the data. CPU 0-d tensors (scalars),
  integer and boolean index tensors, and cross-device ``copy_`` pass, as they do on CUDA;
* ``.cpu()`` gives the plain CPU tensor back; ``.numpy()`` fails, as on a GPU.

``torch.func`` transforms do not take Python tensor subclasses, so :func:`jacfwd` stands in for
``torch.func.jacfwd``: a residual function's own analytic ``.jacobian`` where it has one (as
:func:`torchcal.estimate.problem.jacobian_of` chooses), else columns of Jacobian-vector products by autograd.

Meta tensors alone (no values) stop at the first ``.item()``; this wrapper runs the real thing, about ten
times slower than plain CPU tensors, so tests keep the problems small.
"""

from __future__ import annotations

import contextlib

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

#: the device the wrapped tensors report (any device other than the CPU that every torch build knows)
DEVICE = torch.device("meta")
aten = torch.ops.aten
_INDEX_OPS = {aten.index.Tensor, aten.index_put.default, aten.index_put_.default, aten._index_put_impl_.default}


class Virtual(torch.Tensor):
    """A CPU tensor ``elem`` that reports :data:`DEVICE`."""

    elem: torch.Tensor

    @staticmethod
    def __new__(cls, elem: torch.Tensor):
        r = torch.Tensor._make_wrapper_subclass(
            cls,
            elem.shape,
            strides=elem.stride(),
            storage_offset=elem.storage_offset(),
            dtype=elem.dtype,
            device=DEVICE,
            requires_grad=elem.requires_grad,
        )
        r.elem = elem
        return r

    def tolist(self):
        return self.elem.tolist()

    def __deepcopy__(self, memo):
        # the default deepcopy of a wrapper subclass would rebuild it without its values
        if id(self) not in memo:
            out = Virtual(self.elem.detach().clone()).requires_grad_(self.requires_grad)
            if getattr(self, "_is_param", False):
                out._is_param = True  # nn.Parameter of a tensor subclass: a flag, not a class
            memo[id(self)] = out
        return memo[id(self)]

    def __repr__(self) -> str:
        return f"Virtual({self.elem!r})"

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        return _run(func, args, kwargs or {})


def _items(args, kwargs):
    for a in args:
        if isinstance(a, (list, tuple)):
            yield from a
        else:
            yield a
    yield from kwargs.values()


def _unwrap(a):
    if isinstance(a, Virtual):
        return a.elem
    if isinstance(a, (list, tuple)):
        return type(a)(x.elem if isinstance(x, Virtual) else x for x in a)
    return a


def _is_virtual(device) -> bool:
    return device is not None and torch.device(device) == DEVICE


def _check_indexed(func, args) -> None:
    """Indices on the device into a CPU tensor raise, as on CUDA ("indices should be either on cpu or on the same
    device as the indexed tensor"): only CPU indices into device tensors pass."""
    target = args[0]
    if isinstance(target, Virtual) or not isinstance(target, torch.Tensor) or target.dim() == 0:
        return
    if any(isinstance(i, Virtual) for i in _items(args[1:], {})):
        raise RuntimeError(
            f"{func}: indices on the {DEVICE.type} device into a CPU tensor of shape {tuple(target.shape)}"
        )


def _run(func, args, kwargs):
    virtual = any(isinstance(a, Virtual) for a in _items(args, kwargs))
    to_virtual = _is_virtual(kwargs.get("device"))
    if virtual and func in _INDEX_OPS:
        _check_indexed(func, args)
    if virtual and func is not aten.copy_.default and func is not aten._to_copy.default:
        for a in _items(args, kwargs):
            if isinstance(a, torch.Tensor) and not isinstance(a, Virtual) and a.dim() > 0:
                if func in _INDEX_OPS and not a.is_floating_point():
                    continue  # CPU indices into device tensors are allowed (CUDA too)
                raise RuntimeError(
                    f"{func}: a CPU tensor of shape {tuple(a.shape)} meets tensors on the {DEVICE.type} device "
                    "(a constructor without device=?)"
                )
    uargs = tuple(_unwrap(a) for a in args)
    ukw = {k: _unwrap(v) for k, v in kwargs.items()}
    if to_virtual:
        ukw["device"] = torch.device("cpu")
    out = func(*uargs, **ukw)
    if func is aten.copy_.default:
        return args[0]
    if func is aten._local_scalar_dense.default:
        return out
    if func is aten._to_copy.default:
        wrap = to_virtual or (virtual and "device" not in kwargs)
    else:
        wrap = virtual or to_virtual
    if not wrap:
        return out
    if isinstance(out, torch.Tensor):
        return out if isinstance(out, Virtual) else Virtual(out)
    if isinstance(out, (list, tuple)):
        return type(out)(Virtual(o) if isinstance(o, torch.Tensor) and not isinstance(o, Virtual) else o for o in out)
    return out


_FACTORIES = {
    torch.zeros,
    torch.ones,
    torch.empty,
    torch.full,
    torch.eye,
    torch.arange,
    torch.linspace,
    torch.logspace,
    torch.rand,
    torch.randn,
    torch.randint,
    torch.randperm,
    torch.scalar_tensor,
}


_DATA_DESCRIPTOR = torch._C.TensorBase.__dict__["data"]


def _is_dev(a) -> bool:
    return isinstance(a, (str, torch.device)) and _is_virtual(a)


class _Modes(TorchFunctionMode):
    """Where values would otherwise be lost or land on the CPU unseen, at the Python level:

    * factories and ``torch.tensor``/``torch.as_tensor`` given the virtual device build on the CPU and wrap (the
      dispatcher would make data-less meta tensors);
    * ``Tensor.to`` of a plain tensor to the virtual device (or to the dtype and device of a virtual tensor) wraps
      the CPU result; ``nn.Module.to`` goes through it;
    * a list index of a virtual tensor becomes a CPU index tensor, and a number assigned into one a CPU 0-d tensor
      (what CUDA accepts as well).
    """

    _DATA = (torch.tensor, torch.as_tensor)
    _INDEX = (torch.Tensor.__getitem__, torch.Tensor.__setitem__)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in _FACTORIES and _is_virtual(kwargs.get("device")):
            return Virtual(func(*args, **{**kwargs, "device": "cpu"}))
        if func in self._DATA and _is_virtual(kwargs.get("device")):
            src = args[0] if args else kwargs.get("data")
            if isinstance(src, Virtual):
                return func(*args, **{k: v for k, v in kwargs.items() if k != "device"})
            out = func(*args, **{**kwargs, "device": "cpu"})
            return out if isinstance(out, Virtual) else Virtual(out)
        if func is torch.Tensor.to and not isinstance(args[0], Virtual):
            rest = args[1:]
            if any(_is_dev(a) or isinstance(a, Virtual) for a in rest) or _is_virtual(kwargs.get("device")):
                rest = tuple("cpu" if _is_dev(a) else (a.elem if isinstance(a, Virtual) else a) for a in rest)
                kw = {**kwargs, "device": "cpu"} if "device" in kwargs else kwargs
                return Virtual(func(args[0], *rest, **kw))
        if (
            getattr(func, "__self__", None) is _DATA_DESCRIPTOR
            and func.__name__ == "__set__"
            and isinstance(args[0], Virtual)
        ):
            # ``param.data = x`` (vector_to_parameters): the wrapper keeps its identity, its values are replaced
            args[0].elem = cpu(args[1]).detach()
            return None
        if func in self._INDEX and isinstance(args[0], Virtual):

            def fix(k):
                return torch.tensor(k) if isinstance(k, list) else k

            key = args[1]
            key = tuple(fix(k) for k in key) if isinstance(key, tuple) else fix(key)
            args = (args[0], key, *args[2:])
            if func is torch.Tensor.__setitem__ and isinstance(args[2], (bool, int, float)):
                args = (args[0], key, torch.tensor(args[2], dtype=args[0].dtype))  # a scalar: a CPU 0-d tensor
        return func(*args, **kwargs)


class _Internal(TorchDispatchMode):
    """Factories that torch calls below Python (autograd formulas: ``zeros({}, grad.options())``) with the
    virtual device: built on the CPU and wrapped; everything else passes through."""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if "device" in kwargs and _is_virtual(kwargs["device"]) and not any(isinstance(a, Virtual) for a in args):
            return _run(func, args, kwargs)
        if any(t is Virtual for t in types):
            return NotImplemented  # the subclass handles it
        return func(*args, **kwargs)


def jacfwd(f, has_aux: bool = False):
    """``torch.func.jacfwd`` on virtual tensors (module docstring); with ``has_aux``, ``f`` returns ``(out, aux)``
    and the Jacobian of ``out`` comes with ``aux`` at ``x``."""
    own = getattr(f, "jacobian", None)
    if own is not None and not has_aux:
        return own

    def jac(x: torch.Tensor):
        first = f(x)
        out = first[0] if has_aux else first
        cols = []
        for k in range(x.numel()):
            v = torch.zeros_like(x).flatten()
            v[k] = 1.0
            _, jv = torch.autograd.functional.jvp((lambda y: f(y)[0]) if has_aux else f, x, v.reshape(x.shape))
            cols.append(jv.detach())
        J = torch.stack(cols, dim=-1) if cols else out.new_zeros(*out.shape, 0)
        J = J.reshape(*J.shape[:-1], *x.shape)
        return (J, first[1].detach()) if has_aux else J

    return jac


@contextlib.contextmanager
def virtual_device(monkeypatch=None):
    """Inside it, ``DEVICE`` tensors are CPU tensors in disguise (module docstring); ``torch.func.jacfwd`` is
    replaced by :func:`jacfwd` through ``monkeypatch`` (a pytest fixture) when given."""
    if monkeypatch is not None:
        monkeypatch.setattr(torch.func, "jacfwd", jacfwd)
    with _Internal(), _Modes():
        yield DEVICE


def cpu(x):
    """The plain CPU tensor of a (possibly virtual) tensor."""
    return x.elem if isinstance(x, Virtual) else x
