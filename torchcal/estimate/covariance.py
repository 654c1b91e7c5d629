"""The parameter covariance of a calibration and the standard deviation it gives each prediction.

A fit leaves the covariance ``C = s0^2 N^-1`` of its free parameters (:class:`~torchcal.estimate.lm.LMResult`).
Carried to a prediction ``f(q)`` by its Jacobian ``J = df/dx``, it is ``J C J^T``: how far the positions the model
predicts at ``q`` may be off through the parameters alone, small where the poses determine the geometry and larger
where they leave it weak (far from the poses, along a weak direction). :class:`ParameterCovariance` keeps it by the
parameters' qualified names, so that a run directory stores it beside ``model.pt`` and a reloaded model uses it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.effects import Context, MeasurementModel
from torchcal.errors import EstimationError
from torchcal.estimate.problem import FreeParameters

Tensor = torch.Tensor

#: the largest number of free parameters a stored covariance may hold (a crafted file is refused before use)
MAX_PARAMETERS = 2048


@dataclass
class ParameterCovariance:
    """The covariance ``(u, u)`` of ``u`` free parameter elements, by qualified parameter name and flat index."""

    names: list[str]  # qualified parameter names in the model, one per block
    index: list[list[int]]  # the flat indices of each block's free elements
    labels: list[str]  # one per element, for reports
    matrix: Tensor  # (u, u) [SI units of the parameters]

    @classmethod
    def from_fit(cls, free: FreeParameters, result) -> ParameterCovariance | None:
        """The covariance of a fit's free parameters, or None where its normal matrix is singular."""
        if result.normal is None or result.residuals is None:
            return None
        try:
            C = result.covariance
        except EstimationError:
            return None
        if C.numel() == 0 or not bool(torch.isfinite(C).all()):
            return None
        names = [e.name for e in free.entries]
        index = [[int(i) for i in e.index] for e in free.entries]
        return cls(names, index, list(free.names), C.detach().cpu())

    def state(self) -> dict:
        """A dict of plain lists and one tensor (what ``torch.save`` writes and ``weights_only`` loads)."""
        return {"names": self.names, "index": self.index, "labels": self.labels, "covariance": self.matrix.cpu()}

    @classmethod
    def from_state(cls, state, model: MeasurementModel) -> ParameterCovariance:
        """Rebuild from :meth:`state`, checked against ``model``.

        Raises:
            ValueError: the state is malformed, names a parameter the model lacks or an index beyond it, or holds a
                matrix that is not a finite, symmetric ``(u, u)`` with a non-negative diagonal.
        """
        if not isinstance(state, dict) or set(state) != {"names", "index", "labels", "covariance"}:
            raise ValueError("must hold names, index, labels and covariance")
        names, index, labels, C = state["names"], state["index"], state["labels"], state["covariance"]
        if not (isinstance(names, list) and isinstance(index, list) and len(names) == len(index)):
            raise ValueError("names and index must be lists of the same length")
        params = dict(model.named_parameters())
        u = 0
        for name, idx in zip(names, index):
            if not isinstance(name, str) or name not in params:
                raise ValueError(f"names a parameter the model does not have: {name!r}")
            n = params[name].numel()
            if not isinstance(idx, list) or not idx or not all(isinstance(i, int) and 0 <= i < n for i in idx):
                raise ValueError(f"the indices of {name} must be a non-empty list of integers below {n}")
            u += len(idx)
        if u > MAX_PARAMETERS:
            raise ValueError(f"holds {u} parameters, more than {MAX_PARAMETERS}")
        if not isinstance(labels, list) or len(labels) != u or not all(isinstance(s, str) for s in labels):
            raise ValueError(f"labels must be {u} strings")
        if not isinstance(C, Tensor) or C.shape != (u, u) or C.dtype != torch.float64:
            raise ValueError(f"covariance must be a float64 tensor of shape ({u}, {u})")
        if not bool(torch.isfinite(C).all()) or bool((C.diagonal() < 0).any()):
            raise ValueError("covariance must be finite with a non-negative diagonal")
        if not torch.allclose(C, C.T, rtol=1e-8, atol=1e-300):
            raise ValueError("covariance must be symmetric")
        return cls(list(names), [list(i) for i in index], list(labels), C)

    def free(self, model: MeasurementModel) -> FreeParameters:
        """The model's free parameters this covariance is about, in its order."""
        params = dict(model.named_parameters())
        sel = {}
        for name, idx in zip(self.names, self.index):
            mask = torch.zeros(params[name].numel(), dtype=torch.bool, device=params[name].device)
            mask[idx] = True
            sel[name] = mask.reshape(params[name].shape)
        free = FreeParameters(model, sel)
        # FreeParameters orders a parameter's elements by index: keep the stored order only when it is the same
        if [int(i) for e in free.entries for i in e.index] != [i for idx in self.index for i in sorted(idx)]:
            raise ValueError("the stored indices are not in the model's order")
        return free


def central_jacobian(
    model: MeasurementModel, free: FreeParameters, ctx: Context, steps: Tensor, zero_step: float = 1e-9
) -> Tensor:
    """``d model(ctx) / d free`` ``(N, 3, u)`` by central differences of ``steps`` ``(u,)`` (a step of 0 takes
    ``zero_step``); the model's parameters are restored afterwards."""
    x0 = free.vector()
    J = torch.empty(len(ctx.q), 3, len(x0), dtype=x0.dtype, device=x0.device)
    try:
        with torch.no_grad():
            for k in range(len(x0)):
                h = float(steps[k]) if float(steps[k]) > 0 else zero_step
                step = torch.zeros_like(x0)
                step[k] = h
                free.assign(x0 + step)
                up = model(ctx)
                free.assign(x0 - step)
                J[:, :, k] = (up - model(ctx)) / (2 * h)
    finally:
        free.assign(x0)
    return J


def prediction_std(model: MeasurementModel, ctx: Context, cov: ParameterCovariance) -> Tensor:
    """The standard deviation ``(N, 3)`` [m] of the model's predicted positions at ``ctx`` through its parameters.

    The Jacobian by central differences, one step of each parameter's own standard deviation (the model is linear in
    its parameters over that step to far better than the result needs; no derivative of the effects is required),
    then ``sqrt(diag(J C J^T))`` per axis. The model's parameters are restored afterwards.
    """
    free = cov.free(model)
    x0 = free.vector()
    C = cov.matrix.to(x0)
    sd = C.diagonal().sqrt()
    u = len(x0)
    n = len(ctx.q)
    if u == 0 or n == 0:
        return torch.zeros(n, 3, dtype=x0.dtype, device=x0.device)
    J = central_jacobian(model, free, ctx, sd, zero_step=1e-12)
    var = torch.einsum("nau,uv,nav->na", J, C, J)
    return var.clamp(min=0).sqrt()


def learned_std(model: MeasurementModel, ctx: Context) -> Tensor | None:
    """The posterior standard deviation ``(N, 3)`` [m, tracker frame] of the model's learned corrections where they
    have one (a Gaussian process, the integrated method's gates), faded as the corrections are beyond the calibrated
    region; None where none has."""
    from torchcal.effects.gp import GPCorrection
    from torchcal.effects.grouped import GroupedCorrection, row_groups
    from torchcal.effects.region import predictive_sigma

    def gp_std(e: GPCorrection, sub: Context) -> Tensor:
        return e.predict(sub, std=True)[1]  # robot base frame

    parts = []
    w = model.region_weight(ctx.q)
    R = model.robot.T_tracker_base()[:3, :3]
    with torch.no_grad():
        for e in model.effects:
            if isinstance(e, GPCorrection) and len(e.inducing):
                s = gp_std(e, ctx)
            elif isinstance(e, GroupedCorrection) and any(isinstance(g, GPCorrection) for g in e.inner):
                # each row the std of its own group's GP; rows of a group without one have none
                s = ctx.q.new_zeros(ctx.q.shape[0], 3)
                st, pr = row_groups(ctx)
                for (gs, gp), inner in zip(e.groups, e.inner):
                    rows = torch.nonzero((st == gs) & (pr == gp)).flatten()
                    if isinstance(inner, GPCorrection) and len(inner.inducing) and len(rows):
                        s[rows] = gp_std(inner, ctx.subset(rows))
            else:
                continue
            s = ((R * R) @ s.square().T).T.sqrt()  # per tracker axis, components taken as independent
            parts.append(s if w is None or not e.fades_beyond_region else s * w)
        gate = predictive_sigma(model, ctx.q)
        if gate is not None:
            parts.append(gate)
    if not parts:
        return None
    return torch.stack([p.square() for p in parts]).sum(0).sqrt()


def combined_std(model: MeasurementModel, ctx: Context, cov: ParameterCovariance | None) -> Tensor | None:
    """The predicted standard deviation ``(N, 3)`` [m]: the parameters' (:func:`prediction_std`) and the learned
    corrections' (:func:`learned_std`) added in quadrature; None where the model has neither."""
    # the learned posterior first: a Gaussian process keeps the mean it computes beside its standard deviation, which
    # the parameters' differences then evaluate the model with
    b = learned_std(model, ctx)
    a = prediction_std(model, ctx, cov) if cov is not None else None
    if a is None:
        return b
    return a if b is None else (a.square() + b.square()).sqrt()


def tolerance_bounded(
    cov: ParameterCovariance, model: MeasurementModel, length: float, angle: float
) -> ParameterCovariance:
    """``cov`` with a robot's manufacturing tolerance (``length`` [m], ``angle`` [rad] per geometric element) added as
    information on every geometric element it holds with a variance above the tolerance's: ``C - C H^T (H C H^T +
    P)^-1 H C`` (``H`` picks those elements, ``P`` their tolerance variances). A fit that holds what its rows cannot
    tell at a wider prior (a geometric change's 1 mm, 0.1 deg) says nothing of those elements but that prior; the
    robot's geometry there is no more uncertain than its manufacturing. Only the elements above their tolerance: one
    already held at it (the kinematic calibration's consider covariance) would count that prior twice."""
    units = {i.name: i.unit for i in model.robot.parameter_info() if i.group == "geometry"}
    block = [name for name, idx in zip(cov.names, cov.index) for _ in idx]  # each element's parameter
    C = cov.matrix

    def tol(k: int) -> float:
        return length if units[cov.labels[k]] == "m" else angle

    sel = [
        k
        for k, label in enumerate(cov.labels)
        if block[k] == "robot.geometry.delta" and label in units and float(C[k, k]) > tol(k) ** 2
    ]
    if not sel:
        return cov
    prior = torch.tensor([tol(k) for k in sel], dtype=C.dtype, device=C.device)
    idx = torch.tensor(sel, device=C.device)
    S = C[idx][:, idx] + torch.diag(prior.square())
    CH = C[:, idx]
    out = C - CH @ torch.linalg.solve(S, CH.T)
    out = 0.5 * (out + out.T)
    out.diagonal().clamp_(min=0)
    return ParameterCovariance(list(cov.names), [list(i) for i in cov.index], list(cov.labels), out)
