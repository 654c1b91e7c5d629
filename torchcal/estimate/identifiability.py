"""Which parameters the data can separate, decided from the Jacobian at the data's poses.

Method: normalise every column of the Jacobian to unit length (so metres and radians
compare), then walk the parameters in order of preference and keep a parameter when its
column is independent of the columns kept so far: the sine of the angle between the column
and their span (the norm of its component orthogonal to them) must exceed a tolerance. The
others are held fixed at their current values. This keeps a maximal identifiable set and,
among the possible ones, the one the preference order asks for.

The default preference keeps the instrument pose, then the lever arm, then the robot's
geometry from base to tip, as Horvath & Neuner (2024, Sec. 2.2.3) do: for a UR5 that fixes
``d1, d3, d4, d6, theta1, theta6, alpha6, a6`` in favour of the instrument and lever arm.

Tolerance. Exact dependencies come out at 1e-16..1e-12 (round-off); ``tol = 1e-6`` separates
them from anything a measurement design produces. A robot description with rounded constants
(``1.5708`` for pi/2, as vendors' URDFs write them) turns exact dependencies into near ones
(sine ~ 4e-6) that pass ``tol`` but that no realistic data determine: the fit then keeps pairs
correlated at +-1.000 whose standard deviation is just their prior. So with the a-priori
standard deviations of the parameters (``prior_sigma``) the tolerance comes from the data's
noise and the prior: the Jacobian is whitened by the noise, so the norm ``|v_j|`` of a
column's part orthogonal to the kept span is the data's information on that direction, and
``sigma_data = 1 / |v_j|`` its standard deviation with the kept parameters free. Combined with
the prior, ``sigma_post = (|v_j|^2 + 1 / sigma_prior^2)^-1/2``; the parameter is kept only when
``sigma_post < prior_ratio * sigma_prior``, i.e. its sine must exceed
``sqrt(1 / prior_ratio^2 - 1) / (|J_j| sigma_prior)``. The default ``prior_ratio = 1/sqrt(2)``
keeps a parameter when the data alone determine it better than its prior does
(``sigma_data < sigma_prior``, the data at least halve its variance); otherwise the prior
mostly holds it, and fixing it loses little. Parameters without a prior (inf) keep the
structural ``tol`` alone. The test is conditional on the parameters kept before (greedy): a
later, nearly collinear parameter can still raise an earlier one's marginal deviation.
Parameters that are independent and determined better than their prior are kept and show
their precision through standard deviations and correlations in the report.

After the fit (:func:`weak_after_fit`). The test above is greedy and conditional, and the parameters that come
first in the preference order (instrument pose, lever arm) are kept unless structurally dependent. A weak
direction that only the whole fit reveals (a tool axis that hardly turns across the poses: the lever arm along
it and the instrument's position along it differ only by the tool's tiny turns, and the geometry's freedom
blurs them further) shows in the fit's posterior instead: a parameter with a prior whose posterior standard
deviation is not clearly below the prior's (above ``prior_ratio`` of it, the same ``1/sqrt(2)``), or that is
correlated above :data:`MAX_CORRELATION` with another parameter, is held at its prior value and the fit is
repeated; a pair gives up the member later in the preference order (the lever arm before the instrument pose),
unless the fit puts that member significantly away from its prior value (the data then determine it, correlated or
not: holding it would bias everything else).

For ``n`` rows much more than ``P`` columns the analysis runs on the triangular factor ``R`` of
``J = QR`` (``P x P``): an orthogonal ``Q`` keeps every norm and angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

Tensor = torch.Tensor

DEFAULT_TOL = 1e-6
#: keep a parameter with a prior when data and prior together give it a standard deviation below this fraction of
#: the prior's (module docstring)
DEFAULT_PRIOR_RATIO = 1.0 / math.sqrt(2.0)
#: after the fit, a parameter with a prior correlated beyond this with another is held (:func:`weak_after_fit`):
#: a 0.999 correlation leaves the pair's difference direction with 1/sqrt(1 - 0.999^2) ~ 22 times the sigma either
#: would have alone
MAX_CORRELATION = 0.999
#: the 0.999 quantile of chi-square with one degree of freedom: a held value farther than this (squared, in posterior
#: sigmas) from the fit is one the data reject (:func:`weak_after_fit`)
CHI2_1_999 = 10.828


@dataclass
class Identifiability:
    names: list[str]
    free: Tensor  # (P,) bool: kept
    independence: Tensor  # (P,) sine of the angle to the span of the earlier kept columns (0 for no effect)
    fixed: list[dict] = field(default_factory=list)
    groups: list[list[str]] = field(default_factory=list)
    singular_values: Tensor | None = None  # of the normalised Jacobian, all candidates
    tol: float = DEFAULT_TOL
    prior_ratio: float | None = None  # None: no priors given, the structural tolerance alone
    sigma_data: Tensor | None = None  # (P,) 1/|v_j|: the data's standard deviation of each direction [m or rad]
    weak: list[dict] = field(default_factory=list)  # kept after the fit though correlated beyond MAX_CORRELATION

    @property
    def rank(self) -> int:
        return int(self.free.sum())

    def hold(self, entries: list[dict]) -> None:
        """Mark the parameters of ``fixed`` entries (:func:`weak_after_fit`) as held, with their reasons; entries
        with ``held: False`` are kept in :attr:`weak` instead (one per parameter, the latest)."""
        for e in [e for e in entries if e.get("held") is False]:
            self.weak = [w for w in self.weak if w["name"] != e["name"]] + [e]
        entries = [e for e in entries if e.get("held") is not False]
        for e in entries:
            self.free[self.names.index(e["name"])] = False
            self.fixed.append(e)
        self.groups = _merge(self.groups + [[e["name"], *e["depends_on"]] for e in entries if e["depends_on"]])

    def to_dict(self) -> dict:
        sv = self.singular_values
        return {
            "method": "column-normalised Jacobian; greedy independence test in preference order"
            + (
                "; a parameter with a prior is kept only when the data determine it better than the prior"
                if self.prior_ratio is not None
                else ""
            ),
            "tol": self.tol,
            "prior_ratio": self.prior_ratio,
            "n_candidates": len(self.names),
            "rank": self.rank,
            "fixed": self.fixed,
            "weak": self.weak,
            "dependent_groups": self.groups,
            "condition_number": None
            if sv is None or float(sv[self.rank - 1]) == 0
            else float(sv[0] / sv[self.rank - 1]),
        }


def analyse(
    J: Tensor,
    names: list[str],
    order: list[int] | None = None,
    tol: float = DEFAULT_TOL,
    prior_sigma: Tensor | None = None,
    prior_ratio: float = DEFAULT_PRIOR_RATIO,
) -> Identifiability:
    """Decide which columns of ``J (n, P)`` to keep (module docstring).

    Args:
        J: Jacobian of the (whitened) residuals with respect to the candidate parameters, without the
            priors' pseudo-observations.
        names: the P parameter names.
        order: preference order (indices, most wanted first); default the given order.
        tol: structural independence threshold (sine of the angle to the kept span).
        prior_sigma: a-priori standard deviations ``(P,)`` in the parameters' units (inf: no prior), or None
            for the structural test alone.
        prior_ratio: with ``prior_sigma``, keep a parameter only when data and prior together give it a
            standard deviation below ``prior_ratio`` times its prior's (0 < prior_ratio < 1).
    """
    n, P = J.shape
    order = list(range(P)) if order is None else list(order)
    if n > P:  # the same norms and angles in P dimensions (module docstring)
        J = torch.linalg.qr(J, mode="r").R
        n = P
    norms = J.norm(dim=0)
    scale = float(norms.max()) if P else 1.0
    Jn = J / norms.clamp(min=1e-300)
    # the sine each column needs: the structural tolerance, and where there is a prior, the one from noise and prior
    need = torch.full((P,), float(tol), dtype=J.dtype, device=J.device)
    if prior_sigma is not None:
        if not 0.0 < prior_ratio < 1.0:
            raise ValueError(f"prior_ratio must lie in (0, 1), got {prior_ratio}")
        ps = torch.as_tensor(prior_sigma, dtype=J.dtype, device=J.device).reshape(P)
        has = torch.isfinite(ps) & (ps > 0)
        gain = math.sqrt(1.0 / prior_ratio**2 - 1.0)
        from_prior = gain / (norms * ps).clamp(min=1e-300)
        need = torch.where(has, torch.maximum(need, from_prior), need)
    free = torch.zeros(P, dtype=torch.bool, device=J.device)
    indep = torch.zeros(P, dtype=J.dtype, device=J.device)
    basis = torch.zeros(n, 0, dtype=J.dtype, device=J.device)
    for j in order:
        if float(norms[j]) <= 1e-14 * scale:
            continue  # no effect on the probe at all
        v = Jn[:, j]
        for _ in range(2):  # Gram-Schmidt twice for orthogonality to working precision
            v = v - basis @ (basis.T @ v)
        s = float(v.norm())
        indep[j] = s
        if s > float(need[j]):
            free[j] = True
            basis = torch.cat([basis, (v / s)[:, None]], dim=1)
    sigma_data = 1.0 / (indep * norms).clamp(min=1e-300)

    kept = torch.nonzero(free).flatten()
    fixed, links = [], []
    if len(kept):
        coef = torch.linalg.lstsq(Jn[:, kept], Jn[:, ~free]).solution if int((~free).sum()) else None
    for k, j in enumerate(torch.nonzero(~free).flatten().tolist()):
        if float(norms[j]) <= 1e-14 * scale:
            fixed.append(
                {
                    "name": names[j],
                    "reason": "no effect on the measured positions at these poses",
                    "depends_on": [],
                    "independence": 0.0,
                }
            )
            continue
        c = coef[:, k]
        big = (c.abs() >= 1e-3 * c.abs().max()).nonzero().flatten()
        deps = [names[int(kept[i])] for i in big]
        if float(indep[j]) > tol:
            why = (
                f"nearly dependent on {', '.join(deps)} at these poses (independence {float(indep[j]):.1e}): the "
                f"data determine it to {float(sigma_data[j]):.2g}, no better than its prior "
                f"{float(ps[j]):.2g}; held at its current value"
            )
        else:
            why = (
                f"linearly dependent on {', '.join(deps)} at these poses "
                f"(independence {float(indep[j]):.1e} <= tol {tol:.0e}); held at its current value"
            )
        fixed.append({"name": names[j], "reason": why, "depends_on": deps, "independence": float(indep[j])})
        links.append([names[j], *deps])
    groups = _merge(links)
    sv = torch.linalg.svdvals(Jn[:, norms > 1e-14 * scale]) if P else None
    return Identifiability(
        list(names), free, indep, fixed, groups, sv, tol, prior_ratio if prior_sigma is not None else None, sigma_data
    )


def weak_after_fit(
    names: list[str],
    Q: Tensor,
    prior_sigma: Tensor,
    candidate: Tensor,
    units: dict[str, str] | None = None,
    prior_ratio: float = DEFAULT_PRIOR_RATIO,
    max_correlation: float = MAX_CORRELATION,
    x: Tensor | None = None,
    sigma0_sq: float = 1.0,
    compatible: float = CHI2_1_999,
) -> list[dict]:
    """Which parameters to hold at their prior value after a fit (module docstring, "After the fit").

    Args:
        names: the fitted parameters' names (a pair gives up the later one in :func:`preference_order`).
        Q: ``(P, P)`` the fit's cofactor matrix (normal matrix inverse, priors included, variance factor 1).
        prior_sigma: ``(P,)`` a-priori standard deviations (inf: none).
        candidate: ``(P,)`` bool: the parameters this check may hold (those whose group's prior asks for it); a
            pair with a candidate may also give up a non-candidate with a prior that comes later in the
            preference order.
        units: parameter name -> "m" or "rad", for the reasons' numbers.
        x: ``(P,)`` the fitted values as departures from the priors' centres: with them a correlated parameter is
            held only where its prior value is compatible with the fit, ``x_j^2 / (s0^2 Q_jj) <= compatible``
            (``s0^2``: ``sigma0_sq``, at least 1); a parameter the data pin far from its prior's centre (a lever arm
            along a tool axis that hardly turns, correlated almost perfectly with the instrument's position) is
            determined despite the correlation, and holding it would bias the fit.

    Returns:
        ``fixed`` entries as :class:`Identifiability` writes them (``name``, ``reason``, ``depends_on``,
        ``independence`` = 0): every candidate whose posterior deviation exceeds ``prior_ratio`` of its prior,
        and of the pairs correlated beyond ``max_correlation`` only the most correlated one's later member (holding
        one member decorrelates the others it was tied to; the caller refits and asks again). A correlated
        parameter kept because the fit rejects its prior value comes as an entry with ``held: False`` (a warning
        for the report, :attr:`Identifiability.weak`).
    """
    units = units or {}
    P = len(names)
    ps = torch.as_tensor(prior_sigma, dtype=Q.dtype, device=Q.device).reshape(P)
    has = torch.isfinite(ps) & (ps > 0)
    cand = torch.as_tensor(candidate, dtype=torch.bool, device=Q.device).reshape(P) & has
    sd = Q.diagonal().clamp(min=0).sqrt()

    def fmt(j: int, v: float) -> str:
        return f"{v * 1e3:.3g} mm" if units.get(names[j]) == "m" else f"{v:.3g} rad"

    out = []
    for j in torch.nonzero(cand).flatten().tolist():
        r = float(sd[j] / ps[j])
        if r > prior_ratio:
            out.append(
                {
                    "name": names[j],
                    "reason": f"the fit determines it to {fmt(j, float(sd[j]))}, {r:.2f} of its prior "
                    f"{fmt(j, float(ps[j]))} (above {prior_ratio:.2f}): the data hardly add to the prior; "
                    "held at its prior value",
                    "depends_on": [],
                    "independence": 0.0,
                }
            )
    if out:
        return out
    rho = Q / sd.clamp(min=1e-300)[:, None] / sd.clamp(min=1e-300)[None, :]
    pair = (cand[:, None] | cand[None, :]) & has[:, None] & has[None, :]
    pair &= torch.triu(torch.ones(P, P, dtype=torch.bool, device=Q.device), diagonal=1)
    a = rho.abs().where(pair, torch.zeros_like(rho))
    if P < 2 or float(a.max()) <= max_correlation:
        return out
    rank = {k: n for n, k in enumerate(preference_order(names))}
    order = torch.argsort(a.flatten(), descending=True)
    for flat in order.tolist():
        i, j = divmod(flat, P)
        if float(a[i, j]) <= max_correlation:
            break
        if rank[i] > rank[j]:  # the member later in the preference order is held
            i, j = j, i
        if x is not None:
            s0 = sigma0_sq if math.isfinite(sigma0_sq) and sigma0_sq > 1.0 else 1.0
            z2 = float(x[j]) ** 2 / (s0 * float(Q[j, j]))
            if z2 > compatible:  # the data reject its prior value: determined after all, despite the correlation
                sd_j = fmt(j, math.sqrt(s0 * float(Q[j, j])))
                if not any(e["name"] == names[j] for e in out):
                    out.append(
                        {
                            "name": names[j],
                            "held": False,
                            "reason": f"correlated {float(rho[i, j]):+.4f} with {names[i]} after the fit (beyond "
                            f"{max_correlation}), but fitted {math.sqrt(z2):.1f} sigma ({sd_j}) "
                            "from its prior value, which the data reject: kept; its value rests on that weak "
                            "direction alone (a known value, e.g. --tool for the lever arm, removes the doubt)",
                            "depends_on": [names[i]],
                            "independence": 0.0,
                        }
                    )
                continue
        return out + [
            {
                "name": names[j],
                "reason": f"correlated {float(rho[i, j]):+.4f} with {names[i]} after the fit (beyond "
                f"{max_correlation}): the data do not tell them apart; held at its prior value",
                "depends_on": [names[i]],
                "independence": 0.0,
            }
        ]
    return out


def _merge(links: list[list[str]]) -> list[list[str]]:
    """Union of overlapping name lists, each group in first-seen order."""
    groups: list[list[str]] = []
    for link in links:
        hit = [g for g in groups if set(g) & set(link)]
        merged = []
        for g in hit:
            merged += [x for x in g if x not in merged]
            groups.remove(g)
        merged += [x for x in link if x not in merged]
        groups.append(merged)
    return groups


def preference_order(names: list[str]) -> list[int]:
    """Instrument first, then the lever arm, then everything else in the given order (every station's pose,
    ``instrument[NAME].tx``, and every probe's lever arm, ``tool[NAME].x``, alike)."""

    def rank(i):
        n = names[i]
        return (0 if n.startswith(("instrument.", "instrument[")) else 1 if n.startswith(("tool.", "tool[")) else 2, i)

    return sorted(range(len(names)), key=rank)
