"""Pieces shared by the two filter engines (:mod:`torchcal.filter.ekf`, :mod:`torchcal.filter.adaptive`).

Legend: ``P`` state covariance ``(D, n, n)``; ``H`` observation Jacobian ``(D, 3, n)``; ``U^T = H P`` (``P``
symmetric, so ``U = P H^T``); ``S = H P H^T + R`` the innovation covariance ``(D, 3, 3)``; ``K = U S^-1`` the
gain, carried transposed as ``K^T`` ``(D, 3, n)``; ``NIS = e^T S^-1 e`` per step; ``w`` the network's flat
weights; ``R`` the rotation of ``T_tracker_base``. ``D`` is the leading draw dimension (Monte Carlo draws
filtered together); the adaptive engine uses ``D = 1``.

* :func:`nis_band` and :func:`window_health`: the compatibility test of a window's mean NIS (Sec. 2.1.3 of
  Horvath & Neuner 2024), the variance factor it adapts, and the divergence checks;
* :func:`joseph_update_`: the Joseph-form covariance update as one rank-6 GEMM, in place;
* :class:`NetworkJacobian` (the hand-derived one of :class:`~torchcal.effects.CorrectionNet`) and
  :class:`ModuleJacobian` (any ``nn.Module``, by reverse-mode autodiff): the rotated network output ``R g`` and
  the observation Jacobian ``H = [R dg/dw, I]`` of one step, written into a preallocated ``H``;
* :class:`Gain`: the gain, the NIS and the Joseph update of one step in preallocated buffers;
* :class:`FlatModule`: any ``nn.Module`` seen through one flat weight vector, with the interface of
  :class:`~torchcal.effects.CorrectionNet` that the filters and :func:`~torchcal.estimate.netfit.fit_net` use.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn

from torchcal._torch import backward
from torchcal.effects.learned import CorrectionNet
from torchcal.errors import ShapeError
from torchcal.estimate.lm import chi2_quantile

Tensor = torch.Tensor

#: a window's mean NIS this many times its expectation is a divergence, not a variance factor to adapt
NIS_RUNAWAY = 1e4
#: the variance factor q_yy is kept in this range (a factor outside it means a wrong model, not a scale)
QYY_RANGE = (1e-2, 1e6)


def nis_band(window: int, alpha: float) -> tuple[float, float]:
    """Two-sided band of the mean NIS / 3 over a window (chi-square with ``3 * window`` degrees of freedom)."""
    k = 3 * window
    return chi2_quantile(alpha / 2, k) / k, chi2_quantile(1 - alpha / 2, k) / k


@dataclass
class Health:
    """Outcome of :func:`window_health` per draw: the new variance factor, which draws failed and why."""

    qyy: Tensor  # (D,)
    failed: Tensor  # (D,) bool
    reasons: list[str | None]


def window_health(P: Tensor, nis: Tensor, qyy: Tensor, i: int, band: tuple[float, float], adapt: bool) -> Health:
    """End of a NIS window: symmetrise ``P`` in place, check it and the window's NIS, adapt ``q_yy``.

    The rank-6 update keeps ``P`` symmetric only up to round-off, so it is symmetrised here. Zero variances are
    fixed states; a negative one (beyond round-off) is a diverged filter. A mean NIS of :data:`NIS_RUNAWAY`
    times its expectation is a divergence; outside the chi-square ``band`` (:func:`nis_band`) the variance
    factor ``q_yy`` is scaled by the ratio (the compatibility test of Sec. 2.1.3), within :data:`QYY_RANGE`.

    Args:
        P: ``(D, n, n)`` covariance, symmetrised in place.
        nis: ``(D, window)`` the window's NIS values.
        qyy: ``(D,)`` variance factors.
        i: the window's last sample (for the messages).
    """
    P.copy_(0.5 * (P + P.transpose(-1, -2)))
    pd = P.diagonal(dim1=-2, dim2=-1)
    negative = pd.min(dim=-1).values < -1e-9 * pd.max(dim=-1).values
    ratio = nis.mean(dim=-1) / 3.0
    runaway = ratio > NIS_RUNAWAY
    reasons: list[str | None] = []
    for d in range(len(ratio)):
        if bool(negative[d]):
            reasons.append(f"diverged by sample {i}: negative state variance")
        elif bool(runaway[d]):
            reasons.append(f"diverged at sample {i}: NIS {float(ratio[d]) * 3:.3g} far outside its chi2 band")
        else:
            reasons.append(None)
    failed = negative | runaway
    if adapt:
        out = ((ratio < band[0]) | (ratio > band[1])) & ~failed
        qyy = torch.where(out, (qyy * ratio).clamp(*QYY_RANGE), qyy)
    return Health(qyy, failed, reasons)


def joseph_update_(P: Tensor, Ut: Tensor, Kt: Tensor, S: Tensor) -> Tensor:
    """Joseph-form update ``(I - K H) P (I - K H)^T + K R K^T`` in place, as one rank-6 GEMM.

    With ``U = P H^T`` and ``S = H P H^T + R`` the Joseph form expands to ``P - K U^T - U K^T + K S K^T``
    ``= P + [-K, K S - U] [U, K]^T``: one ``(n, 6) x (6, n)`` product accumulated into ``P`` (no copy of ``P``,
    no ``n x n`` temporary). It holds for any gain ``K``, which is why it is preferred to ``P - K S K^T``.

    Args:
        P: ``(D, n, n)`` or ``(n, n)``; Ut, Kt: ``(D, 3, n)`` or ``(3, n)``; S: ``(D, 3, 3)`` or ``(3, 3)``.
    """
    At = torch.cat([-Kt, S @ Kt - Ut], dim=-2)
    Bt = torch.cat([Ut, Kt], dim=-2)
    if P.ndim == 3:
        return P.baddbmm_(At.mT, Bt)
    return P.addmm_(At.T, Bt)


class Gain:
    """Gain, innovation statistics and the Joseph update of one step, in preallocated buffers ``(D, ...)``.

    One ``(D, 9, n)`` buffer holds ``[U^T; K^T; U^T - S K^T]``. The Joseph form of :func:`joseph_update_`,
    ``P + [-K, K S - U] [U, K]^T``, is then ``P - A^T B`` with ``A`` its last six rows and ``B`` its first six:
    two views of the same buffer, so a step allocates nothing of size ``n`` and negates nothing. The 3x3 ``S``
    is factored by Cholesky (``info`` says where it is not positive definite) and inverted from the factor:
    ``K^T = S^-1 U^T``; the state update ``K e = U (S^-1 e)`` and ``NIS = e^T (S^-1 e)`` need only ``S^-1 e``.

    Args:
        D: draws; n: state dimension; like: a tensor of the dtype and device to use.
    """

    def __init__(self, D: int, n: int, like: Tensor):
        kw = {"dtype": like.dtype, "device": like.device}
        self.C = torch.empty(D, 9, n, **kw)
        self.Ut, self.Kt, self.Mt = self.C[:, :3], self.C[:, 3:6], self.C[:, 6:]
        self.AT, self.B = self.C[:, 3:].mT, self.C[:, :6]

    def gain(self, H: Tensor, HT: Tensor, P: Tensor, R: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``U^T = H P``, ``S = H P H^T + R`` and its Cholesky factor; ``info`` nonzero where ``S`` is not PD.

        Args:
            H: ``(D, 3, n)``; HT: its transposed view; P: ``(D, n, n)``; R: ``(D, 3, 3)`` observation covariance.
        """
        Ut = torch.bmm(H, P, out=self.Ut)
        S = torch.baddbmm(R, Ut, HT)
        L, info = torch.linalg.cholesky_ex(S)
        return S, L, info

    def solve(self, L: Tensor, e: Tensor, se: Tensor) -> Tensor:
        """``K^T (D, 3, n)`` (in the buffer), and ``S^-1 e`` written into ``se (D, 3, 1)`` for ``e (D, 3, 1)``."""
        Si = torch.cholesky_inverse(L)
        torch.bmm(Si, e, out=se)
        return torch.bmm(Si, self.Ut, out=self.Kt)

    def joseph_(self, P: Tensor, S: Tensor) -> Tensor:
        """:func:`joseph_update_` with the buffered ``U^T`` and ``K^T``: ``P - [K, U - K S] [U, K]^T``."""
        torch.baddbmm(self.Ut, S, self.Kt, alpha=-1.0, out=self.Mt)
        return P.baddbmm_(self.AT, self.B, alpha=-1.0)


# ----------------------------------------------------------------------------------- networks
class FlatModule(nn.Module):
    """Any ``nn.Module`` mapping joints ``(N, dof)`` to corrections ``(N, 3)`` [m], seen through one flat weight
    vector, with the methods of :class:`~torchcal.effects.CorrectionNet` that the filters and
    :func:`~torchcal.estimate.netfit.fit_net` use (``flat``, ``set_flat``, ``forward_flat``, ``jacobian_flat``,
    ``n_weights``). Weights are ordered as ``module.parameters()``; the Jacobians come from ``torch.func``.

    Args:
        module: the user's network (float64 on the calibration path). It is held, not copied.
        dof: the number of joints it takes (checked once on a probe input).
    """

    def __init__(self, module: nn.Module, dof: int):
        super().__init__()
        self.module = module
        self.dof = dof
        params = list(module.named_parameters())
        if not params:
            raise ShapeError("the correction network has no parameters to estimate")
        self._names = [n for n, _ in params]
        self._shapes = [p.shape for _, p in params]
        self._sizes = [p.numel() for _, p in params]
        p0 = params[0][1]
        with torch.no_grad():
            out = module(torch.zeros(2, dof, dtype=p0.dtype, device=p0.device))
        if out.shape != (2, 3):
            raise ShapeError(
                f"the correction network must map joints (N, {dof}) to corrections (N, 3), it gave "
                f"{tuple(out.shape)} for N = 2"
            )

    @property
    def n_weights(self) -> int:
        return sum(self._sizes)

    def forward(self, q: Tensor) -> Tensor:
        return self.module(q)

    def flat(self) -> Tensor:
        """The weights as one vector ``(n_weights,)`` in the order of ``module.parameters()``."""
        return torch.nn.utils.parameters_to_vector(self.module.parameters()).detach().clone()

    def set_flat(self, w: Tensor) -> None:
        torch.nn.utils.vector_to_parameters(w.detach().clone(), self.module.parameters())

    def unflat(self, w: Tensor) -> dict[str, Tensor]:
        """Views of a flat ``w (n_weights,)`` as the module's named parameters (differentiable in ``w``)."""
        return {n: t.view(s) for n, t, s in zip(self._names, torch.split(w, self._sizes), self._shapes)}

    def _single(self, w: Tensor, q: Tensor) -> Tensor:
        return torch.func.functional_call(self.module, self.unflat(w), (q,))

    def forward_flat(self, w: Tensor, q: Tensor) -> Tensor:
        """Output ``(..., N, 3)`` for flat weights ``w (..., n_weights)`` and joints ``q (..., N, dof)``."""
        if w.ndim == 1:
            return self._single(w, q)
        lead = torch.broadcast_shapes(w.shape[:-1], q.shape[:-2])
        wf = w.expand(*lead, w.shape[-1]).reshape(-1, w.shape[-1])
        qf = q.expand(*lead, *q.shape[-2:]).reshape(-1, *q.shape[-2:])
        return torch.func.vmap(self._single)(wf, qf).reshape(*lead, q.shape[-2], 3)

    def jacobian_flat(self, w: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
        """Output ``(N, 3)`` and its Jacobian ``dg/dw (N, 3, n_weights)`` at ``w (n_weights,)``, ``q (N, dof)``."""

        def one(wv, qi):
            out = self._single(wv, qi[None])[0]
            return out, out

        J, g = torch.func.vmap(torch.func.jacrev(one, has_aux=True), in_dims=(None, 0))(w, q)
        return g.detach(), J.detach()


def as_flat(net: nn.Module, dof: int) -> CorrectionNet | FlatModule:
    """``net`` itself when it is a :class:`CorrectionNet` (it has the flat interface), else a :class:`FlatModule`."""
    if isinstance(net, (CorrectionNet, FlatModule)):
        return net
    return FlatModule(net, dof)


class NetworkJacobian:
    """The rotated network output ``R g`` and ``H = [R dg/dw, I]`` at one sample, for a :class:`CorrectionNet`.

    Hand-derived (equal to ``R @ CorrectionNet.jacobian_flat``) and written straight into a preallocated ``H``:
    the rotation folds into the blocks (``R (ds x^T) = (R ds) x^T`` for the first layer, ``R (I kron a) = R
    kron a`` for the second), the constant blocks (output bias, the identity for the position) are set once,
    the inputs are normalised once, and every product writes into its block (``out=``), so a step creates no
    tensor of the size of ``H``.

    Args:
        net: the network (its architecture and normalisation; the weights come with each call).
        q: joints ``(D, N, dof)`` of the whole pass [rad]; R: ``(3, 3)``; D: draws.
    """

    def __init__(self, net: CorrectionNet, q: Tensor, R: Tensor, D: int):
        Hn, Dq = net.hidden, net.dof
        self.Hn, self.Dq = Hn, Dq
        self.x = ((q - net.q_offset) / net.q_scale).unsqueeze(-1)  # (D, N, dof, 1)
        self.Ros = R * float(net.out_scale)  # the rotation with the network's output scale folded in
        nw = net.n_weights
        self.o1, self.o2, self.o3 = Hn * Dq, Hn * Dq + Hn, Hn * Dq + 4 * Hn
        kw = {"dtype": q.dtype, "device": q.device}
        self.H = torch.zeros(D, 3, nw + 3, **kw)
        self.H[:, :, self.o3 : nw] = self.Ros  # output bias block: R os
        self.H[:, :, nw:] = torch.eye(3, **kw)  # the position block
        # views of H's blocks, each written in place by one product per step
        self.H_W1 = self.H[:, :, : self.o1].view(D, 3, Hn, Dq)
        self.H_b1 = self.H[:, :, self.o1 : self.o2]
        self.H_W2 = self.H[:, :, self.o2 : self.o3].view(D, 3, 3, Hn)
        self.Ros4 = self.Ros[None, :, :, None]
        self.RosD = self.Ros.expand(D, 3, 3).contiguous()
        self.RW2 = torch.empty(D, 3, Hn, **kw)
        self.ng = torch.empty(D, 3, 1, **kw)
        self.ones = torch.ones(D, Hn, 1, **kw)
        self.HT = self.H.mT
        # views made once (a step's every op counts): the inputs as rows, the hidden-bias block with an axis
        self.xT = self.x.view(*self.x.shape[:2], 1, 1, Dq)
        self.H_b1_4 = self.H_b1.unsqueeze(-1)
        self._views: tuple | None = None

    def bind(self, w: Tensor) -> None:
        """Views of the weights ``w (D, n_w)``: valid as long as ``w`` is only updated in place."""
        Hn, Dq, D = self.Hn, self.Dq, w.shape[0]
        self._views = (
            w[:, : self.o1].view(D, Hn, Dq),
            w[:, self.o1 : self.o2].unsqueeze(-1),
            w[:, self.o2 : self.o3].view(D, 3, Hn),
            w[:, self.o3 :].unsqueeze(-1),
        )

    def __call__(self, w: Tensor, i: int) -> tuple[Tensor, Tensor]:
        """``R g (D, 3)`` and ``H (D, 3, n_w + 3)`` (the internal buffer) at sample ``i`` for weights ``w``."""
        if self._views is None or self._views[0].data_ptr() != w.data_ptr():
            self.bind(w)
        W1, b1, W2, b2 = self._views
        a = torch.tanh(torch.baddbmm(b1, W1, self.x[:, i]))  # (D, H, 1)
        ng = torch.bmm(self.RosD, torch.baddbmm(b2, W2, a), out=self.ng)[..., 0]
        torch.bmm(self.RosD, W2, out=self.RW2)
        torch.mul(self.RW2, torch.addcmul(self.ones, a, a, value=-1.0).mT, out=self.H_b1)  # d(R g)/dz
        torch.mul(self.H_b1_4, self.xT[:, i], out=self.H_W1)
        torch.mul(self.Ros4, a.view(a.shape[0], 1, 1, self.Hn), out=self.H_W2)
        return ng, self.H


class ModuleJacobian:
    """The same as :class:`NetworkJacobian` for any network, by reverse-mode autodiff.

    Exact, like the hand-derived one. Per step: one forward of the module per draw, then three backward passes
    through the same graph whose cotangents are the rows of ``R``, so they give the rows of ``R dg/dw``
    directly. The module runs as a private copy whose parameters are leaves sharing storage with the filter's
    weights (a step copies no weights), and whose gradient buffers are views of ``H``: before backward pass
    ``k`` they are pointed at row ``k``, so the backward accumulates into ``H`` and nothing is copied out of
    gradients. The backward passes go straight to the engine (:func:`torchcal._torch.backward`: the public
    wrapper's argument handling costs as much as a small backward). ``torch.func`` (``vmap(jacrev)`` of
    ``functional_call``, as :meth:`FlatModule.jacobian_flat` and the baseline use) gives the same numbers, but its
    per-call parameter swapping and transforms cost several Kalman steps, and a ``vmap``-batched backward
    (``is_grads_batched``) no less than three plain ones; ``scripts/bench_ekf.py`` measures this path against the
    hand-derived one.

    Args:
        net: a :class:`FlatModule` (or a :class:`CorrectionNet`, to compare with the hand-derived Jacobian).
        q: joints ``(D, N, dof)`` [rad]; R: ``(3, 3)``; D: draws.
    """

    def __init__(self, net: CorrectionNet | FlatModule, q: Tensor, R: Tensor, D: int):
        self.q, self.R = q, R
        module = net.module if isinstance(net, FlatModule) else net
        self.copies = [copy.deepcopy(module) for _ in range(D)]
        # (owner, name) of every parameter of each copy in parameters() order, recorded here because bind replaces
        # the parameters by plain tensors, which the module then no longer lists as parameters
        self.slots = [[(m, n) for m in c.modules() for n, _ in m.named_parameters(recurse=False)] for c in self.copies]
        nw = net.n_weights
        kw = {"dtype": q.dtype, "device": q.device}
        self.H = torch.zeros(D, 3, nw + 3, **kw)
        self.H[:, :, nw:] = torch.eye(3, **kw)
        self.HT, self.Hw = self.H.mT, self.H[:, :, :nw]
        self.cot = [R[k].expand(D, 3).contiguous() for k in range(3)]  # row k of R, for every draw
        self.ptr = -1
        self.leaves: list[Tensor] = []
        self.rows: list[list[Tensor]] = [[], [], []]

    def bind(self, w: Tensor) -> None:
        """Make the copies' parameters leaves that alias ``w (D, n_w)`` (updated in place by the filter), and
        the views of ``H``'s three rows that serve as their gradients.

        One leaf per parameter (not views of one flat leaf): the backward then has no slicing nodes that would
        each allocate a gradient of the whole weight vector.
        """
        self.ptr, self.leaves, self.rows = w.data_ptr(), [], [[], [], []]
        for d, slots in enumerate(self.slots):
            off = 0
            for mod, name in slots:
                p = getattr(mod, name)
                n = p.numel()
                leaf = w[d, off : off + n].view(p.shape).detach().requires_grad_(True)  # shares w's storage
                for k in range(3):
                    self.rows[k].append(self.H[d, k, off : off + n].view(p.shape))
                off += n
                delattr(mod, name)  # the parameter (at the first bind) or the previous leaf
                setattr(mod, name, leaf)
                self.leaves.append(leaf)

    def __call__(self, w: Tensor, i: int) -> tuple[Tensor, Tensor]:
        if self.ptr != w.data_ptr():
            self.bind(w)
        self.Hw.zero_()
        with torch.enable_grad():
            g = torch.cat([c(self.q[d, i : i + 1]) for d, c in enumerate(self.copies)])  # (D, 3)
            for k in range(3):  # cotangent k is row k of R: the backward accumulates row k of R dg/dw into H
                for leaf, row in zip(self.leaves, self.rows[k]):
                    leaf.grad = row
                backward(g, self.cot[k], k < 2)
        return g.detach() @ self.R.T, self.H
