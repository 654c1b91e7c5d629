"""Which poses to measure: a greedy D-optimal choice among candidate poses, and the error it predicts.

Legend (one pose ``i``, ``P`` identifiable parameters of the geometry, the instrument pose and the lever arm):

- ``J_i (3, P)``: the probe position's Jacobian in the tracker frame [m per m or rad]
  (:meth:`~torchcal.robot.model.RobotModel.tracker_jacobian`);
- ``C_i = diag(s^2) + sigma_q^2 J_q J_q^T`` the measurement covariance and ``A_i = L_i^-1 J_i`` the whitened
  Jacobian (:func:`~torchcal.estimate.problem.whitening`, the stochastic model of every fit);
- ``M_0 = diag(1 / prior^2)`` the priors' information, ``M(S) = M_0 + sum_{i in S} A_i^T A_i`` that of a set ``S``;
  ``Sigma(S) = s0^2 M(S)^-1`` the parameters' covariance for a variance factor ``s0^2`` (1 where the stochastic
  model is right; a run's own on real data, where unmodelled errors act as extra noise).

Criterion: maximise ``log det M(S)`` (D-optimal). It is invariant to the parameters' units and to any invertible
reparameterisation, so the choice does not depend on which member of a dependent group the identifiability
analysis kept, and it shrinks the volume of the whole confidence ellipsoid rather than one direction (an
A-optimal design would depend on the units chosen for lengths against angles).

Greedy, one pose at a time (D): by the matrix determinant lemma adding pose ``i`` raises ``log det M`` by
``log det(I_3 + A_i Sigma A_i^T)`` (``Sigma = M^-1``), a 3x3 determinant per candidate, and Woodbury updates
``Sigma <- Sigma - Sigma A_i^T (I_3 + A_i Sigma A_i^T)^-1 A_i Sigma`` with one 3x3 solve: a pick costs
``O(N 3 P^2)`` for ``N`` candidates (no ``P x P`` factorisation per candidate). Greedy selection of a monotone
submodular set function (``log det`` is one) is within ``1 - 1/e`` of the best set of its size (Nemhauser et al.,
1978), and the choices are nested: the first ``k`` of ``K`` picks are the greedy design for ``k``.

The I criterion (the default) minimises instead what the prediction below measures, the mean position variance
over the candidates ``tr(W Sigma)`` with ``W = mean_e J_e^T J_e`` (I-optimal: the prediction variance integrated over
the region): by Woodbury a pick lowers it by ``tr((I_3 + A_i Sigma A_i^T)^-1 A_i Sigma W Sigma A_i^T)``, again 3x3
per candidate, at about twice the D criterion's cost. It is unit-free too, but depends on the region (the candidates):
it spends poses on the directions that move the probe where the robot works, not on parameter directions that barely
do. On the real UR10 (Series A, docs/real-data.md) its designs score better than the D criterion's at every size.

Prediction (``predicted_rmse``): a new pose ``e`` measured after calibrating on ``S`` misses by the parameters' error
and its own measurement noise, ``E|e|^2 = tr(J_e Sigma(S) J_e^T) + s0^2 tr(C_e)``; averaged over evaluation poses
(the candidates: the region the robot will work in) that is the predicted held-out RMSE. It assumes the model is
right up to the noise (a variance factor ``s0^2`` absorbs unmodelled errors only as far as they look like noise).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from torchcal import _console
from torchcal.effects.base import Context
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.estimate.identifiability import DEFAULT_TOL, Identifiability, analyse, preference_order
from torchcal.estimate.problem import probe_joint_jacobian, whitening

Tensor = torch.Tensor

#: the parameter groups a design is made for: those a kinematic calibration fits
DESIGN_GROUPS = ("geometry", "instrument", "tool")
#: prior standard deviation [m or rad] given to a parameter without one, so that ``M_0`` is invertible: a kilometre
#: or a thousand radians, no information at all on the scale of any measurement
UNINFORMATIVE = 1e3


@dataclass(frozen=True)
class Priors:
    """A-priori standard deviations of the corrections, as :class:`torchcal.pipeline.Options` sets them by default.

    ``length`` [m] and ``angle`` [rad] for the geometry; ``instrument`` (position [m], rotation [rad]) about the
    start; ``lever`` [m] for the lever arm. None: no prior (:data:`UNINFORMATIVE`).
    """

    length: float | None = 1e-3
    angle: float | None = math.radians(0.1)
    instrument: tuple[float, float] | None = (0.5, 0.1)
    lever: float | None = 0.5

    def sigma(self, group: str, unit: str) -> float:
        if group == "geometry":
            v = self.length if unit == "m" else self.angle
        elif group == "instrument":
            v = None if self.instrument is None else self.instrument[0 if unit == "m" else 1]
        else:
            v = self.lever
        return UNINFORMATIVE if v is None else float(v)


@dataclass
class DesignProblem:
    """The candidates' Jacobians by the identifiable parameters (module legend).

    Attributes:
        names, units: the identifiable parameters' names and units (``m`` or ``rad``), ``P`` of them.
        J: ``(N, 3, P)`` tracker-frame Jacobian per candidate [m per unit].
        A: ``(N, 3, P)`` whitened Jacobian ``L_i^-1 J_i``.
        noise: ``(N,)`` ``tr C_i`` [m^2], the measurement's own variance per candidate.
        prior_info: ``(P,)`` ``1 / prior^2``, the diagonal of ``M_0``.
        identifiability: the analysis of all candidates together (what no choice among them can determine is held).
    """

    names: list[str]
    units: list[str]
    J: Tensor
    A: Tensor
    noise: Tensor
    prior_info: Tensor
    identifiability: Identifiability

    @property
    def n(self) -> int:
        return int(self.J.shape[0])


def design_problem(
    model: MeasurementModel,
    q: Tensor,
    *,
    sigma_tracker: float = 15e-6,
    sigma_joint: float = math.radians(0.0005),
    priors: Priors | None = None,
    rank_tol: float = DEFAULT_TOL,
) -> DesignProblem:
    """The design problem of ``model``'s robot (its current geometry, instrument pose and lever arm) at candidate
    poses ``q (N, dof)`` [rad], with the fits' stochastic model (``sigma_tracker`` [m] per axis, ``sigma_joint``
    [rad]) and ``priors``; the parameters are those of :data:`DESIGN_GROUPS` the identifiability analysis of all
    candidates keeps."""
    robot = model.robot
    if robot.stations or robot.probes:
        raise OptionError(
            "planning poses for several instrument stations or probes at once is not supported; plan per station "
            "(torchcal plan --run RUN --station S --probe P)"
        )
    priors = priors or Priors()
    unit_of = {i.name: i.unit for i in robot.parameter_info()}
    groups = robot.groups()
    columns, names, units, prior = [], [], [], []
    for g in DESIGN_GROUPS:
        grp = groups[g]
        for i in torch.nonzero(grp.mask.flatten()).flatten().tolist():
            columns.append((g, i))
            names.append(grp.names[i])
            units.append(unit_of.get(grp.names[i], "m"))
            prior.append(priors.sigma(g, units[-1]))
    ctx = Context(q=q)
    with torch.no_grad():
        _, J = robot.tracker_jacobian(q, columns)
        W = whitening(model, ctx, None, sigma_tracker, sigma_joint)
        A = W @ J
        noise = torch.full((len(q),), 3.0 * sigma_tracker**2, dtype=q.dtype, device=q.device)
        if sigma_joint > 0:
            Jq = probe_joint_jacobian(model, ctx)
            noise = noise + sigma_joint**2 * Jq.square().sum(dim=(1, 2))
    ps = torch.tensor(prior, dtype=q.dtype, device=q.device)
    ps_finite = torch.where(ps >= UNINFORMATIVE, torch.full_like(ps, float("inf")), ps)
    ida = analyse(A.reshape(-1, len(names)), names, preference_order(names), tol=rank_tol, prior_sigma=ps_finite)
    keep = ida.free
    return DesignProblem(
        names=[n for n, k in zip(names, keep.tolist()) if k],
        units=[u for u, k in zip(units, keep.tolist()) if k],
        J=J[:, :, keep],
        A=A[:, :, keep],
        noise=noise,
        prior_info=1.0 / ps[keep].square(),
        identifiability=ida,
    )


@dataclass
class Design:
    """A greedy D-optimal order of candidates.

    Attributes:
        order: ``(K,)`` candidate indices in the order picked (the first ``k`` are the design for ``k``).
        log_det: ``(K,)`` ``log det M`` after each pick.
        information: ``k -> M`` ``(P, P)`` at the requested checkpoints.
    """

    order: Tensor
    log_det: Tensor
    information: dict[int, Tensor] = field(default_factory=dict)


def information(problem: DesignProblem, index: Tensor) -> Tensor:
    """``M(S) (P, P)`` of the candidates ``index``."""
    A = problem.A[index].reshape(-1, problem.A.shape[-1])
    return torch.diag(problem.prior_info) + A.T @ A


def log_det(problem: DesignProblem, index: Tensor) -> float:
    """``log det M(S)`` of the candidates ``index`` (the D criterion)."""
    return float(torch.linalg.slogdet(information(problem, index)).logabsdet)


#: the criteria :func:`greedy_design` knows
CRITERIA = ("D", "I")


def greedy_design(
    problem: DesignProblem,
    k: int,
    *,
    criterion: str = "I",
    restrict: Tensor | None = None,
    every: int = 0,
    checkpoints: tuple[int, ...] = (),
    other: Callable[[int, Tensor], Tensor | None] | None = None,
) -> Design:
    """Pick ``k`` candidates greedily by the I or the D criterion (module docstring).

    Args:
        criterion: ``"I"`` (minimise the mean position variance over the candidates, ``tr(W M^-1)``) or ``"D"``
            (maximise ``log det M``).
        restrict: ``(N,)`` bool; with ``every > 0`` every ``every``-th pick (picks ``every``, ``2 every``, ...) is
            made among these candidates only (poses at the edges of the region: any prefix holds its share).
        checkpoints: pick counts at which to keep ``M`` (for the curve of predicted error against ``k``).
        other: ``(j, taken) -> scores (N,)`` or None: where it returns scores, pick ``j`` (0-based) is the candidate
            with the highest score among those not taken (another criterion's turn; ``taken`` is the ``(N,)`` bool
            of the picks so far).
    """
    N = problem.n
    if not 1 <= k <= N:
        raise OptionError(f"can pick 1 to {N} poses from {N} candidates, asked for {k}")
    A = problem.A
    P = A.shape[-1]
    A2 = A.reshape(-1, P)
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    Sigma = torch.diag(1.0 / problem.prior_info)
    M = torch.diag(problem.prior_info.clone())
    ld = float(problem.prior_info.log().sum())
    taken = torch.zeros(N, dtype=torch.bool, device=A.device)
    if criterion not in CRITERIA:
        raise OptionError(f"unknown design criterion {criterion!r}; valid: {', '.join(CRITERIA)}")
    W = mean_information(problem) if criterion == "I" else None
    order, history, kept = [], [], {}
    for j in _console.progress(range(k), desc="plan: picks"):
        B = (A2 @ Sigma).reshape(N, 3, P)  # A_i Sigma
        G = eye + B @ A.transpose(1, 2)  # I + A_i Sigma A_i^T
        d_gain = torch.linalg.slogdet(G).logabsdet
        if W is None:
            gain = d_gain
        else:  # the drop of tr(W Sigma) by Woodbury: tr(G_i^-1 B_i W B_i^T)
            Q = (B.reshape(-1, P) @ W).reshape(N, 3, P) @ B.transpose(1, 2)
            gain = torch.linalg.solve(G, Q).diagonal(dim1=1, dim2=2).sum(-1)
        blocked = taken.clone()
        if restrict is not None and every > 0 and (j + 1) % every == 0 and bool((restrict & ~taken).any()):
            blocked |= ~restrict
        gain = gain.masked_fill(blocked, -math.inf)
        turn = other(j, taken) if other is not None else None
        i = int(torch.argmax(gain if turn is None else turn.masked_fill(taken, -math.inf)))
        u = B[i].T  # Sigma A_i^T (P, 3)
        Sigma = Sigma - u @ torch.linalg.solve(G[i], u.T)
        Sigma = 0.5 * (Sigma + Sigma.T)
        M = M + A[i].T @ A[i]
        ld += float(d_gain[i])
        taken[i] = True
        order.append(i)
        history.append(ld)
        if j + 1 in checkpoints:
            kept[j + 1] = M.clone()
    return Design(
        torch.tensor(order, dtype=torch.long, device=A.device),
        torch.tensor(history, dtype=A.dtype, device=A.device),
        kept,
    )


def greedy_d_optimal(problem: DesignProblem, k: int, **kw) -> Design:
    """:func:`greedy_design` by the D criterion."""
    return greedy_design(problem, k, criterion="D", **kw)


def mean_information(problem: DesignProblem) -> Tensor:
    """``W = mean_e J_e^T J_e (P, P)`` over the candidates: ``tr(W Sigma)`` is their mean position variance [m^2]."""
    J = problem.J.reshape(-1, problem.J.shape[-1])
    return J.T @ J / problem.n


def mean_variance(problem: DesignProblem, index: Tensor) -> float:
    """``tr(W M(S)^-1)`` [m^2]: the mean position variance over the candidates after ``index`` (the I criterion)."""
    return float((mean_information(problem) @ covariance(information(problem, index))).trace())


def covariance(M: Tensor, s0_sq: float = 1.0) -> Tensor:
    """``Sigma = s0^2 M^-1 (P, P)`` by Cholesky."""
    L = torch.linalg.cholesky(M)
    return s0_sq * torch.cholesky_inverse(L)


def predicted_rmse(J: Tensor, noise: Tensor, Sigma: Tensor, s0_sq: float = 1.0) -> float:
    """Predicted held-out RMSE [m] over evaluation poses with Jacobians ``J (E, 3, P)`` and measurement variances
    ``noise (E,)`` [m^2] for a parameter covariance ``Sigma`` (already scaled by ``s0^2``): module docstring."""
    spread = torch.einsum("eap,pq,eaq->e", J, Sigma, J)
    return float((spread + s0_sq * noise).mean().sqrt())
