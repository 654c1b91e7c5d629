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
from torchcal._bounds import SIGMA_JOINT
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
    sigma_joint: float = SIGMA_JOINT,
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


def _cholesky3(G: Tensor) -> tuple[Tensor, ...]:
    """The Cholesky factor ``L`` of 3x3 symmetric positive definite matrices stored by element, ``G (3, 3, N)``:
    ``(l00, l10, l11, l20, l21, l22)``, each ``(N,)``. By hand on whole vectors: a batched factorisation of ``N``
    3x3 matrices costs more than these few sums, and unlike a determinant by cofactors it stays accurate where the
    priors make ``G`` large and nearly singular (the first picks)."""
    l00 = G[0, 0].sqrt()
    l10, l20 = G[1, 0] / l00, G[2, 0] / l00
    l11 = (G[1, 1] - l10 * l10).sqrt()
    l21 = (G[2, 1] - l20 * l10) / l11
    l22 = (G[2, 2] - l20 * l20 - l21 * l21).sqrt()
    return l00, l10, l11, l20, l21, l22


def _log_det3(L: tuple[Tensor, ...]) -> Tensor:
    """``log det G (N,)`` from its Cholesky factor (:func:`_cholesky3`)."""
    return 2.0 * (L[0].log() + L[2].log() + L[5].log())


def _trace_solve3(L: tuple[Tensor, ...], Q: Tensor) -> Tensor:
    """``tr(G^-1 Q) (N,)`` for ``G = L L^T`` (:func:`_cholesky3`) and symmetric ``Q (3, 3, N)`` stored by element:
    ``sum_k m_k Q m_k^T`` over the rows ``m_k`` of ``L^-1``."""
    l00, l10, l11, l20, l21, l22 = L
    m00, m11, m22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
    m10 = -l10 * m00 * m11
    m21 = -l21 * m11 * m22
    m20 = (l10 * l21 - l20 * l11) * m00 * m11 * m22
    q00, q11, q22 = Q[0, 0], Q[1, 1], Q[2, 2]
    q01, q02, q12 = 0.5 * (Q[0, 1] + Q[1, 0]), 0.5 * (Q[0, 2] + Q[2, 0]), 0.5 * (Q[1, 2] + Q[2, 1])
    row0 = m00 * m00 * q00
    row1 = m10 * m10 * q00 + 2.0 * m10 * m11 * q01 + m11 * m11 * q11
    row2 = (
        m20 * m20 * q00
        + m21 * m21 * q11
        + m22 * m22 * q22
        + 2.0 * (m20 * m21 * q01 + m20 * m22 * q02 + m21 * m22 * q12)
    )
    return row0 + row1 + row2


def _outer(X: Tensor, Y: Tensor) -> Tensor:
    """``X_n Y_n^T`` per candidate of ``(3, 3, N)`` matrices stored by element (a reduction over an outer dimension:
    ``N`` 3x3 products as one vectorised pass, where a batched matmul of 3x3 blocks is slow)."""
    return (X[:, None] * Y[None, :]).sum(2)


class _Woodbury:
    """The greedy loop's state, kept current by rank-3 updates (module docstring): ``Sigma = M^-1 (P, P)``,
    per candidate ``G_c = I_3 + A_c Sigma A_c^T`` and, for the I criterion, ``Q_c = A_c Sigma W Sigma A_c^T``
    (both stored by element, ``(3, 3, N)``).

    A pick ``i`` changes ``Sigma`` by ``-u H u^T`` (``u = Sigma A_i^T (P, 3)``, ``H = G_i^-1``), so with
    ``V_c = A_c u``, ``S_c = A_c Sigma W u`` (``(3, 3)``, one pass over ``A``) and ``m = u^T W u``:
    ``G_c <- G_c - V_c H V_c^T`` and ``Q_c <- Q_c - S_c H V_c^T - V_c H S_c^T + V_c H m H V_c^T``. A pick reads
    the candidates' whitened Jacobians once and writes 18 numbers per candidate, where forming ``A Sigma`` again
    wrote ``3 P`` and took ``3 P^2`` products (the cost that made 100,000 candidates hang). The state is formed again
    from ``Sigma`` every :data:`RESYNC` picks and after a pick that cancels digits (:data:`RESYNC_GAIN`).
    """

    def __init__(self, A: Tensor, Sigma: Tensor, W: Tensor | None):
        self.A2, self.W = A.reshape(-1, A.shape[-1]), W
        self.At = A.permute(1, 2, 0).contiguous()  # (3, P, N): a pick's products as three plain GEMMs
        self.N, _, self.P = A.shape
        self.eye = torch.eye(3, dtype=A.dtype, device=A.device)[:, :, None]
        self.picks = 0
        self.form(Sigma)

    def _quadratic(self, X: Tensor) -> Tensor:
        """``A_c X A_c^T`` for ``X (P, P)``, stored by element ``(3, 3, N)``, in blocks of candidates (memory)."""
        out = torch.empty(3, 3, self.N, dtype=X.dtype, device=X.device)
        for lo in range(0, self.N, BLOCK):
            Ab = self.A2[3 * lo : 3 * (lo + BLOCK)]
            L = (Ab @ X).reshape(-1, 3, self.P)
            out[:, :, lo : lo + BLOCK] = (L @ Ab.reshape(-1, 3, self.P).transpose(1, 2)).permute(1, 2, 0)
        return out

    def form(self, Sigma: Tensor) -> None:
        """``G`` (and ``Q``) from ``Sigma`` directly."""
        self.Sigma = Sigma
        self.G = self.eye + self._quadratic(Sigma)
        if self.W is not None:
            self.Q = self._quadratic(Sigma @ self.W @ Sigma)

    def gains(self) -> tuple[Tensor, Tensor]:
        """``(N,)`` the rise of ``log det M`` (the D gain) and the criterion's gain (the same for D; for I the drop
        of ``tr(W Sigma)``, ``tr(G_c^-1 Q_c)``)."""
        L = _cholesky3(self.G)
        d_gain = _log_det3(L)
        if self.W is None:
            return d_gain, d_gain
        return d_gain, _trace_solve3(L, self.Q)

    def pick(self, i: int) -> None:
        """Fold candidate ``i`` into the state (Woodbury, rank 3)."""
        self.picks += 1
        u = self.Sigma @ self.A2[3 * i : 3 * i + 3].T  # (P, 3)
        Gi = self.G[:, :, i]
        # a solve, not u G_i^-1 u^T: while the priors dominate G_i is nearly singular at its scale and an explicit
        # inverse loses the digits Sigma's downdate keeps
        Sigma = self.Sigma - u @ torch.linalg.solve(Gi, u.T)
        H = torch.linalg.inv(Gi)  # used where no update cancels digits (below)
        H = 0.5 * (H + H.T)
        Sigma = 0.5 * (Sigma + Sigma.T)
        if self.picks % RESYNC == 0:
            self.form(Sigma)
            return
        # one pass over A for every 3x3 block the updates need: A_c u, A_c u H and, for I,
        # A_c (s H - u H m H / 2) with s = Sigma W u (the old Sigma), whose outer product with A_c u taken with its
        # transpose is Q's change S H V^T + V H S^T - V H m H V^T
        cols = [u, u @ H]
        if self.W is not None:
            cols.append((self.Sigma @ (self.W @ u)) @ H - 0.5 * u @ (H @ (u.T @ self.W @ u) @ H))
        self.Sigma = Sigma
        X = torch.matmul(torch.cat(cols, 1).T, self.At)  # (3, 6 or 9, N)
        V = X[:, :3]
        dG = _outer(X[:, 3:6], V)
        G = self.G - dG
        # an update that shrinks some candidate's G by more than a factor RESYNC_GAIN cancels that many digits of
        # it (and of its Q): form the state anew instead (the first picks, while the priors dominate)
        shrink = max(float((dG[a, a] / G[a, a]).max()) for a in range(3))
        if not shrink < RESYNC_GAIN:
            self.form(Sigma)
            return
        self.G = G
        if self.W is not None:
            F = _outer(X[:, 6:], V)
            self.Q = self.Q - F - F.transpose(0, 1)


#: candidates per block where the greedy loop's state is formed (bounds the ``(3 BLOCK, P)`` temporaries)
BLOCK = 4096
#: the greedy loop's state (:class:`_Woodbury`) is formed again from ``Sigma`` every this many picks, and after a
#: pick that shrinks a diagonal element of some candidate's ``G`` by more than ``RESYNC_GAIN`` (cancelled digits)
RESYNC = 64
RESYNC_GAIN = 10.0


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
    if criterion not in CRITERIA:
        raise OptionError(f"unknown design criterion {criterion!r}; valid: {', '.join(CRITERIA)}")
    A = problem.A
    state = _Woodbury(A, torch.diag(1.0 / problem.prior_info), mean_information(problem) if criterion == "I" else None)
    M = torch.diag(problem.prior_info.clone())
    ld = float(problem.prior_info.log().sum())
    taken = torch.zeros(N, dtype=torch.bool, device=A.device)
    order, history, kept = [], [], {}
    for j in _console.progress(range(k), desc="plan: picks"):
        d_gain, gain = state.gains()
        blocked = taken.clone()
        if restrict is not None and every > 0 and (j + 1) % every == 0 and bool((restrict & ~taken).any()):
            blocked |= ~restrict
        gain = gain.masked_fill(blocked, -math.inf)
        turn = other(j, taken) if other is not None else None
        i = int(torch.argmax(gain if turn is None else turn.masked_fill(taken, -math.inf)))
        state.pick(i)
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
