"""Score tests of candidate effects at the current least-squares fit.

Legend: ``r`` whitened residuals ``(n,)`` and ``J`` their Jacobian ``(n, u)`` with respect to the
current free parameters, both at the solution; ``C (n, k)`` the whitened Jacobian of the
predictions with respect to one candidate's ``k`` parameters at zero; ``s0^2 = r^T r / (n - u)``.

Adding the candidate and refitting lowers the weighted sum of squares, to first order, by

    dSS = r^T P r,   P the orthogonal projector onto the part of span(C) orthogonal to span(J)

(the Lagrange multiplier or score test of the linearised model; Rao 1948, Breusch & Pagan
1980). When the candidate is absent, ``dSS / s0^2`` is chi-square with ``k`` degrees of
freedom. The ``K`` candidates are tested at once, so their p-values are Bonferroni-corrected
(``min(1, K p)``) before any is compared with the level; the couplings between pairs of joints count as one
member of that family, Bonferroni over the pairs within it (a weighted Bonferroni,
:func:`~torchcal.diagnose.candidates.bonferroni_factors`), so that the ``dof (dof - 1)`` pairs do not take the
power of the other tests. The change of the Bayesian information
criterion ``-dSS / s0^2 + k ln n`` is reported next to it (negative: the candidate pays for its
parameters).

A candidate the current model already explains cannot be tested: its columns are checked with
:func:`torchcal.estimate.identifiability.analyse` against the current ones, and a candidate with
any column dependent on them (sine of the angle to their span <= tol) is marked not identifiable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal import _dual
from torchcal.diagnose.candidates import Candidate, bonferroni_factors
from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.identifiability import DEFAULT_TOL, analyse
from torchcal.estimate.lm import LMResult
from torchcal.estimate.problem import linear_kinematics
from torchcal.stats import chi2_sf_log10

Tensor = torch.Tensor


@dataclass
class Score:
    """The evidence for one candidate (module docstring)."""

    candidate: Candidate
    k: int
    delta_ss: float  # first-order decrease of the whitened sum of squares
    statistic: float  # delta_ss / s0^2, chi-square(k) without the effect
    p_value: float
    log10_p: float  # for ranking where p underflows
    p_bonferroni: float
    bic_change: float
    independence: float  # smallest sine of a candidate column to the current span
    identifiable: bool
    n_candidates: int
    factor: int = 0  # what p was multiplied by (weighted Bonferroni: candidates.bonferroni_factors); 0: n_candidates

    def significant(self, alpha: float) -> bool:
        return self.identifiable and self.p_bonferroni < alpha

    def to_dict(self) -> dict:
        return {
            **self.candidate.to_dict(),
            "test": "score test (chi-square) on the linearised model",
            "n_params": self.k,
            "delta_ss": self.delta_ss,
            "statistic": self.statistic,
            "dof": self.k,
            "p_value": self.p_value,
            "log10_p": self.log10_p,
            "p_bonferroni": self.p_bonferroni,
            "n_candidates": self.n_candidates,
            "bonferroni_factor": self.factor or self.n_candidates,
            "bic_change": self.bic_change,
            "independence": self.independence,
            "identifiable": self.identifiable,
        }


def candidate_columns(model: MeasurementModel, cand: Candidate, ctx: Context, p: Tensor, W: Tensor, fk=None) -> Tensor:
    """Whitened Jacobian ``C (3N, k)`` of the predictions w.r.t. the candidate's parameters at zero.

    ``fk``: the model's kinematics linearised at the current fit (:func:`~torchcal.estimate.problem.linear_kinematics`),
    shared by all candidates: the same columns without differentiating the chain of every pose per candidate.
    """
    eff = cand.make()
    trial = MeasurementModel(model.robot, [*model.effects, eff])
    i = len(model.effects)
    names = [n for n, _ in eff.named_parameters()]
    shapes = [q.shape for _, q in eff.named_parameters()]
    sizes = [q.numel() for _, q in eff.named_parameters()]

    def fun(theta: Tensor) -> Tensor:
        parts = torch.split(theta, sizes)
        params = {f"effects.{i}.{n}": v.reshape(s) for n, v, s in zip(names, parts, shapes)}
        pred = torch.func.functional_call(trial, params, (ctx,), {"fk": fk} if fk is not None else None)
        return (W @ _dual.sub(pred, p).unsqueeze(-1)).reshape(-1)  # torchcal._dual: p is constant

    theta0 = torch.zeros(sum(sizes), dtype=torch.float64, device=p.device)
    return torch.func.jacfwd(fun)(theta0).detach()


#: the most poses x candidate parameters that :func:`all_candidate_columns` differentiates in one pass
COLUMN_BUDGET = 4_000_000


def all_candidate_columns(
    model: MeasurementModel, cands: list[Candidate], ctx: Context, p: Tensor, W: Tensor, fk=None
) -> list[Tensor]:
    """:func:`candidate_columns` of every candidate from one ``jacfwd`` of the model with all of them added.

    Each candidate's parameters are zero, so every added effect contributes exact zeros to the prediction and to
    the other candidates' tangents: each candidate's columns are those of the model with it alone, and the model's
    forward pass runs once instead of once per candidate. Where a column is not finite (an effect whose zero
    contribution carries a NaN into the other candidates' tangents) the candidates are differentiated one by one.
    """
    n_rows = p.shape[0]
    batches, batch, width = [], [], 0
    for c in cands:  # batches of at most COLUMN_BUDGET rows x tangents (jacfwd's memory grows with both)
        k = c.n_params
        if batch and (width + k) * n_rows > COLUMN_BUDGET:
            batches.append(batch)
            batch, width = [], 0
        batch.append(c)
        width += k
    if batch:
        batches.append(batch)
    return [C for b in batches for C in _columns_together(model, b, ctx, p, W, fk)]


def _columns_together(model: MeasurementModel, cands: list[Candidate], ctx: Context, p: Tensor, W: Tensor, fk):
    effs = [c.make() for c in cands]
    trial = MeasurementModel(model.robot, [*model.effects, *effs])
    first = len(model.effects)
    keys, shapes, sizes, per = [], [], [], []
    for i, eff in enumerate(effs):
        named = list(eff.named_parameters())
        keys += [f"effects.{first + i}.{n}" for n, _ in named]
        shapes += [v.shape for _, v in named]
        sizes += [v.numel() for _, v in named]
        per.append(sum(v.numel() for _, v in named))

    def fun(theta: Tensor) -> Tensor:
        params = {k: v.reshape(sh) for k, v, sh in zip(keys, torch.split(theta, sizes), shapes)}
        pred = torch.func.functional_call(trial, params, (ctx,), {"fk": fk} if fk is not None else None)
        return (W @ _dual.sub(pred, p).unsqueeze(-1)).reshape(-1)  # torchcal._dual: p is constant

    C = torch.func.jacfwd(fun)(torch.zeros(sum(sizes), dtype=torch.float64, device=p.device)).detach()
    if not bool(torch.isfinite(C).all()):
        return [candidate_columns(model, c, ctx, p, W, fk) for c in cands]
    return list(torch.split(C, per, dim=1))


def score_candidates(
    model: MeasurementModel,
    result: LMResult,
    ctx: Context,
    p: Tensor,
    W: Tensor,
    *,
    cands: list[Candidate],
    tol: float = DEFAULT_TOL,
) -> list[Score]:
    """Score every candidate at the fit ``result`` of ``model`` to ``p`` (module docstring); best first.

    Args:
        result: the least-squares fit, with whitened residuals and Jacobian at its solution (prior
            pseudo-observations, if any, come after the ``3N`` observations).
        ctx, p, W: the samples, measured positions ``(N, 3)`` and whitening ``(N, 3, 3)`` of that fit.
    """
    r, J = result.residuals, result.jacobian
    n_obs = 3 * ctx.q.shape[0]
    extra = len(r) - n_obs
    s0sq = result.sigma0_sq
    scale = J.norm(dim=0).clamp(min=1e-300)
    Q, R1 = torch.linalg.qr(J / scale)
    u = J.shape[1]
    K = len(cands)
    factors = bonferroni_factors(cands)
    out = []
    fk = linear_kinematics(model, ctx) if cands else None
    for cand, f, C in zip(cands, factors, all_candidate_columns(model, cands, ctx, p, W, fk)):
        if extra:
            C = torch.cat([C, torch.zeros(extra, C.shape[1], dtype=C.dtype, device=C.device)])
        k = C.shape[1]
        # the part of the candidate's columns orthogonal to the current span (projected twice for round-off), and
        # with it the triangular factor of [J, C] by blocks, [[R1, Q^T C], [0, R_c]]: analyse() on it sees every norm
        # and angle of the 3N-row matrix (orthogonal factors keep them) without factorising [J, C] per candidate
        Cn = C / C.norm(dim=0).clamp(min=1e-300)
        B = torch.zeros(u, k, dtype=C.dtype, device=C.device)
        for _ in range(2):
            b = Q.T @ Cn
            Cn = Cn - Q @ b
            B = B + b
        Qc, Rc = torch.linalg.qr(Cn)
        R = torch.cat(
            [torch.cat([R1, B], dim=1), torch.cat([torch.zeros(k, u, dtype=C.dtype, device=C.device), Rc], dim=1)]
        )
        ida = analyse(R, [f"x{i}" for i in range(u + k)], tol=tol)
        indep = float(ida.independence[u:].min())
        identifiable = bool(ida.free[u:].all())
        if identifiable:
            keep = Rc.diagonal().abs() > tol
            dss = float((Qc[:, keep].T @ r).square().sum())
        else:
            dss = 0.0
        stat = dss / s0sq if s0sq > 0 else float("inf")
        pv, l10 = chi2_sf_log10(stat, k)
        out.append(
            Score(cand, k, dss, stat, pv, l10, min(1.0, f * pv), -stat + k * math.log(n_obs), indep, identifiable, K, f)
        )
    # ranked by the corrected p (a coupling's weight is a share of one member's)
    out.sort(key=lambda s: (not s.identifiable, s.log10_p + math.log10(s.factor), -s.statistic))
    return out


def named_p(evidence: dict) -> str:
    """The one p-value a decision rests on, with the test's name, as every report and message prints it:
    ``"localisation of tau2: Bonferroni p = 3.8e-207"`` for an open candidate (admitted on the localisation of the
    residual in that variable), ``"score test: Bonferroni p = 0.00071"`` for a named one.

    Args:
        evidence: a score's ``to_dict()`` (:class:`Score` or the localisation's), or a report's ``evidence`` of it.
    """
    p = evidence.get("p_bonferroni")
    p_words = "-" if p is None else f"{p:.2g}"
    if str(evidence.get("test", "")).startswith("localisation"):
        var = (evidence.get("localisation") or {}).get("variable") or evidence.get("variable")
        return f"localisation{f' of {var}' if var else ''}: Bonferroni p = {p_words}"
    return f"score test: Bonferroni p = {p_words}"
