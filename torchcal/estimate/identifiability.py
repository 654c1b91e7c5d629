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
not: holding it would bias everything else). A pair is the smallest case of a weak *combination*
(:func:`weak_combinations`: an eigen-direction of the unit-diagonal normal matrix, a lever arm with every station's
offset, a ratio with the geometry); its candidate member carrying most of it is held the same way, and held even
against the data where they put it beyond :data:`PRIOR_CONFLICT` prior sigmas. A held member keeps its prior's doubt
in the run's covariance (:func:`torchcal.estimate.fit.considered`).

After a fit about a prior (:func:`detectability`): whether the rows could have told a move of each parameter.

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
    #: the parameters :meth:`hold` put back at their prior value: their prior's uncertainty stays in the run's
    #: covariance (:func:`torchcal.estimate.fit.considered`), so a prediction that depends on them says so
    prior_held: list[str] = field(default_factory=list)

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
            self.prior_held.append(e["name"])
        self.groups = _merge(self.groups + [[e["name"], *e["depends_on"]] for e in entries if e["depends_on"]])

    def combinations(self) -> list[str]:
        """One line per weak combination found after the fit (:func:`weak_combinations`): its member held at its prior
        value, or kept and named, with the reason (for stderr; report.json carries the entries)."""
        out = [f"`{e['name']}` held: {e['reason']}" for e in self.fixed if e.get("combination")]
        return out + [f"`{e['name']}` weakly determined: {e['reason']}" for e in self.weak if e.get("combination")]

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
    need, ps = _needed_sines(norms, tol, prior_sigma, prior_ratio)
    free, indep = _keep_independent(Jn, norms, order, need, scale)
    sigma_data = 1.0 / (indep * norms).clamp(min=1e-300)
    fixed, links = _held_columns(Jn, norms, scale, free, indep, sigma_data, names, tol, ps)
    groups = _merge(links)
    sv = torch.linalg.svdvals(Jn[:, norms > 1e-14 * scale]) if P else None
    return Identifiability(
        list(names), free, indep, fixed, groups, sv, tol, prior_ratio if prior_sigma is not None else None, sigma_data
    )


def _needed_sines(norms: Tensor, tol: float, prior_sigma: Tensor | None, prior_ratio: float):
    """The sine each column needs to be kept: the structural tolerance, and where there is a prior, the one from
    noise and prior. Returns ``(need (P,), prior sigmas (P,) or None)``."""
    P = len(norms)
    need = torch.full((P,), float(tol), dtype=norms.dtype, device=norms.device)
    ps = None
    if prior_sigma is not None:
        if not 0.0 < prior_ratio < 1.0:
            raise ValueError(f"prior_ratio must lie in (0, 1), got {prior_ratio}")
        ps = torch.as_tensor(prior_sigma, dtype=norms.dtype, device=norms.device).reshape(P)
        has = torch.isfinite(ps) & (ps > 0)
        gain = math.sqrt(1.0 / prior_ratio**2 - 1.0)
        from_prior = gain / (norms * ps).clamp(min=1e-300)
        need = torch.where(has, torch.maximum(need, from_prior), need)
    return need, ps


def _keep_independent(Jn: Tensor, norms: Tensor, order: list[int], need: Tensor, scale: float):
    """Walk the columns in preference order, keeping each whose sine to the kept span exceeds its ``need``:
    ``(free (P,) bool, sine (P,))``."""
    n, P = Jn.shape
    free = torch.zeros(P, dtype=torch.bool, device=Jn.device)
    indep = torch.zeros(P, dtype=Jn.dtype, device=Jn.device)
    basis = torch.zeros(n, 0, dtype=Jn.dtype, device=Jn.device)
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
    return free, indep


def _held_columns(Jn, norms, scale: float, free, indep, sigma_data, names, tol: float, ps):
    """Each held column's entry of ``Identifiability.fixed`` (its reason and the kept columns it depends on), and
    the dependency links ``[held, *depends_on]`` the dependent groups are merged from."""
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
    return fixed, links


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
        and of the weak combinations (:func:`weak_combinations`: a pair correlated beyond ``max_correlation``, or
        any number of parameters as weakly tied) only the weakest one's member latest in the preference order
        (holding one member frees the others it was tied to; the caller refits and asks again), its entry naming
        the ``combination``. A member kept because the fit rejects its prior value comes as an entry with
        ``held: False`` (a warning for the report, :attr:`Identifiability.weak`), unless the fitted value lies more
        than :data:`PRIOR_CONFLICT` prior sigmas from the prior's: then it is held all the same (:func:`_judge`).
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
    for combo in weak_combinations(names, Q, has, max_correlation):
        entry = _judge(names, Q, ps, cand, combo, fmt, x, sigma0_sq, compatible, max_correlation)
        if entry is None:
            continue
        if entry.get("held") is not False:
            return out + [entry]  # one hold per round: the caller refits and asks again
        out.append(entry)
    return out


@dataclass(frozen=True)
class WeakCombination:
    """A direction in parameter space the fit hardly determines: the smallest eigen-directions of the normal matrix
    scaled to unit diagonal (:func:`weak_combinations`)."""

    names: tuple[str, ...]  # its members, largest share first
    indices: tuple[int, ...]  # their positions in the fit's parameters
    direction: tuple[float, ...]  # (len(names),) a move of the members that the data hardly see [m or rad]
    eigenvalue: float  # of the unit-diagonal normal matrix: 1 - |rho| for a pair, 0 for an exact dependency
    #: the members whose holding settles a weak direction (the unit-diagonal normal matrix without them has one
    #: eigenvalue fewer below the bound): a member with a small share leaves the combination as weak as it was
    cures: tuple[int, ...] = ()
    shares: tuple[float, ...] = ()  # each member's share of the unit eigenvector (squared component), summing to <= 1

    def describe(self) -> str:
        """``tool.z - 0.33 instrument[S1].tx + ...``: the move, scaled to 1 on the first member, in m and rad."""
        d = self.direction
        terms = [f"{self.names[0]}"] + [
            f"{'-' if c / d[0] < 0 else '+'} {abs(c / d[0]):.2g} {n}" for n, c in zip(self.names[1:], d[1:])
        ]
        return " ".join(terms)


#: a member of a weak combination carries at least this share of its (unit) eigenvector's squared length
MEMBER_SHARE = 0.01


def weak_combinations(names: list[str], Q: Tensor, among: Tensor, max_correlation: float = MAX_CORRELATION):
    """The combinations of parameters the fit leaves weak, weakest first.

    Method: the normal matrix ``N = Q^-1`` scaled to unit diagonal (``N_s = D^-1/2 N D^-1/2``, ``D = diag N``);
    an eigenvalue ``mu`` of ``N_s`` is the squared sine between its direction and the span of the others'
    (:func:`analyse`'s independence, for a combination instead of one column). A pair correlated ``rho`` has
    ``mu = 1 - |rho|``, so ``mu < 1 - max_correlation`` is the pairwise rule for any number of members: a lever arm
    along a tool axis that never turns, with every station's offset along it; a readings ratio with the geometry;
    an effect with the geometry. The members are the parameters carrying :data:`MEMBER_SHARE` of the eigenvector.

    Args:
        names: the ``P`` fitted parameters.
        Q: ``(P, P)`` the fit's cofactor matrix (priors included).
        among: ``(P,)`` bool: a combination counts only where it has at least one such member (those with a prior).

    Returns:
        :class:`WeakCombination` per eigenvalue below ``1 - max_correlation``, weakest first.
    """
    sd = Q.diagonal().clamp(min=1e-300).sqrt()
    C = Q / sd[:, None] / sd[None, :]
    L, info = torch.linalg.cholesky_ex(C)
    if int(info) != 0 or len(names) < 2:
        return []
    Ci = torch.cholesky_inverse(L)  # D_Q^1/2 N D_Q^1/2
    r = Ci.diagonal().clamp(min=1e-300).sqrt()
    mu, V = torch.linalg.eigh(Ci / r[:, None] / r[None, :])
    Ns = Ci / r[:, None] / r[None, :]
    mu, V = torch.linalg.eigh(Ns)
    scale = sd / r  # y = x / scale: the coordinates of N_s
    bound = 1.0 - max_correlation
    weak = int((mu < bound).sum())
    out = []
    for k in range(weak):
        v = V[:, k]
        idx = sorted((i for i in range(len(names)) if float(v[i]) ** 2 >= MEMBER_SHARE), key=lambda i: -abs(v[i]))
        if len(idx) < 2 or not any(bool(among[i]) for i in idx):
            continue
        d = tuple(float(v[i] * scale[i]) for i in idx)
        cures = tuple(i for i in idx if _weak_without(Ns, i, bound) < weak)
        share = tuple(float(v[i]) ** 2 for i in idx)
        out.append(WeakCombination(tuple(names[i] for i in idx), tuple(idx), d, float(mu[k]), cures, share))
    return out


def _weak_without(Ns: Tensor, i: int, bound: float) -> int:
    """How many eigenvalues of the unit-diagonal normal matrix ``Ns`` lie below ``bound`` once parameter ``i`` is
    held (its row and column gone)."""
    keep = torch.arange(len(Ns), device=Ns.device) != i
    return int((torch.linalg.eigvalsh(Ns[keep][:, keep]) < bound).sum())


#: a weak combination's member is held only where it carries at least this share of the direction (of the unit
#: eigenvector, in the unit-diagonal coordinates; a pair's members carry half each, a lever arm along a still tool axis
#: with four stations' offsets 0.50): a minor member (a URDF's joint origins tied with the lever arm at 7 %) leaves the
#: direction to the others, and holding it would only bias them by its own doubt
HOLD_SHARE = 0.25

#: a weak combination's member fitted further than this many a-priori sigmas from its prior value is held even where
#: the data reject that value: the data pin the combination by its weak part alone, and a value the prior rules out
#: there is the model's error amplified (a lever arm 3.15 m along a tool axis that never turned, 6.3 sigma of its
#: 0.5 m prior), not information
PRIOR_CONFLICT = 3.0


def _judge(names, Q, ps, cand, combo: WeakCombination, fmt, x, sigma0_sq, compatible, max_correlation) -> dict | None:
    """The :func:`weak_after_fit` entry of one weak combination: its candidate member latest in
    :func:`preference_order` (of those carrying :data:`HOLD_SHARE` whose holding settles it) is held (``held:
    False``: kept and named, where the data reject its prior value and the prior allows the fitted one, or where no
    candidate settles it), or None where no member is a candidate."""
    has = torch.isfinite(ps) & (ps > 0)
    if not any(bool(cand[i]) for i in combo.indices if bool(has[i])):
        return None
    members = [i for i in combo.cures if bool(cand[i]) and combo.shares[combo.indices.index(i)] >= HOLD_SHARE]
    if not members:  # no member with a prior settles it alone: named, for the report
        j = next(i for i in combo.indices if bool(cand[i]) and bool(has[i]))
        why = "no member this check may hold (a lever arm, instrument pose or ratio) carries a quarter of it: kept"
        return {
            "name": names[j],
            "held": False,
            "reason": f"part of a weak combination after the fit, {combo.describe()} (independence "
            f"{math.sqrt(max(combo.eigenvalue, 0.0)):.1e}): {why}; its value rests on that weak direction",
            "depends_on": [names[i] for i in combo.indices if i != j],
            "independence": 0.0,
            "combination": list(combo.names),
        }
    rank = {k: n for n, k in enumerate(preference_order(names))}
    j = max(members, key=lambda i: (rank[i], -combo.indices.index(i)))
    others = [names[i] for i in combo.indices if i != j]
    if len(combo.indices) == 2:
        i = next(i for i in combo.indices if i != j)
        rho = float(Q[i, j] / (Q[i, i] * Q[j, j]).sqrt())
        what = f"correlated {rho:+.4f} with {names[i]} after the fit (beyond {max_correlation})"
    else:
        what = (
            f"part of a weak combination after the fit, {combo.describe()} (independence "
            f"{math.sqrt(max(combo.eigenvalue, 0.0)):.1e}): a move along it hardly changes the measured positions"
        )
    entry = {"name": names[j], "depends_on": others, "independence": 0.0, "combination": list(combo.names)}
    if x is not None:
        s0 = sigma0_sq if math.isfinite(sigma0_sq) and sigma0_sq > 1.0 else 1.0
        z2 = float(x[j]) ** 2 / (s0 * float(Q[j, j]))
        away = abs(float(x[j])) / float(ps[j])
        if z2 > compatible and away <= PRIOR_CONFLICT:  # the data reject its prior value and the prior allows theirs
            entry["held"] = False
            entry["reason"] = (
                f"{what}, but fitted {math.sqrt(z2):.1f} sigma ({fmt(j, math.sqrt(s0 * float(Q[j, j])))}) from its "
                "prior value, which the data reject: kept; its value rests on that weak direction alone (a known "
                "value, e.g. --tool for the lever arm, removes the doubt)"
            )
            return entry
        if z2 > compatible:
            entry["reason"] = (
                f"{what}; fitted {fmt(j, float(x[j]))} from its prior value, {away:.1f} of its prior sigma "
                f"{fmt(j, float(ps[j]))} (beyond {PRIOR_CONFLICT:g}): the data pin it by that weak direction alone, "
                "at a value the prior rules out (the model's error, amplified); held at its prior value (a known "
                "value, e.g. --tool for the lever arm, or poses that turn it, determine it)"
            )
            return entry
    entry["reason"] = f"{what}: the data do not tell them apart; held at its prior value"
    return entry


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


#: a calibration from a prior run asks whether its rows could have told a move of this many prior sigmas of each
#: parameter (:func:`detectability`): a crash of 2 mrad on a joint is about 10 of a UR10 calibration's (0.19 mrad)
DETECT_SIGMAS = 10.0


@dataclass(frozen=True)
class Detectability:
    """Whether a fit about a prior could have told a move of each parameter (:func:`detectability`)."""

    names: tuple[str, ...]
    share: tuple[float, ...]  # (P,) the share of a move of each parameter its own change shows (0..1)
    #: name, share, detectable_from (the smallest move seen, in prior sigmas), absorbed_by, rows_needed (to tell it)
    untold: tuple[dict, ...]
    k: float  # the move asked about, in prior sigmas
    threshold: float  # a change counts as moved beyond this many prior sigmas
    rows: int  # the rows the fit had
    rows_needed: int | None  # rows like these for every untold parameter to be told (None: nothing untold)

    @property
    def confounded(self) -> list[str]:
        """The untold parameters and those their moves go to, in order of first mention."""
        out: list[str] = []
        for u in self.untold:
            out += [n for n in [u["name"], *u["absorbed_by"]] if n not in out]
        return out

    def to_dict(self) -> dict:
        return {
            "move_sigma": self.k,
            "threshold_sigma": self.threshold,
            "rows": self.rows,
            "cannot_tell": [dict(u) for u in self.untold],
            "confounded": self.confounded,
            "rows_needed": self.rows_needed,
            "poses_to_add": None if self.rows_needed is None else max(self.rows_needed - self.rows, 0),
        }


def detectability(
    names: list[str],
    N: Tensor,
    fit_sigma: Tensor,
    test_sigma: Tensor,
    rows: int,
    k: float = DETECT_SIGMAS,
    threshold: float = 3.0,
) -> Detectability:
    """Which parameters' moves a fit about a prior (MAP, each parameter with an a-priori sigma) could have told.

    A true change ``delta`` of parameter ``j`` moves the fit's estimate by ``Q N_d e_j delta`` (linearised), ``Q`` the
    cofactor (priors included), ``N_d = N - diag(1 / s^2)`` the rows' own information: parameter ``j`` itself shows
    ``r_j = 1 - Q_jj / s_j^2`` of it, the rest goes to the parameters it is confounded with (``-Q_ij / s_j^2`` each).
    A move of ``k`` test sigmas is told where its own change passes the test, ``r_j k > threshold``; else it is
    *untold*: the rows could not have said it moved, and "nothing moved" would be a silent miss. More rows like these
    scale ``N_d``; ``rows_needed`` is the fewest (``t N_d``, ``t`` found by bisection) that tell every untold one,
    None where even a thousand times the rows would not (a direction these poses never separate: other poses must).

    Args:
        names: the ``P`` fitted parameters.
        N: ``(P, P)`` the fit's normal matrix at its solution, the priors' pseudo-observations included.
        fit_sigma: ``(P,)`` the a-priori sigmas the fit used (inf: none) [m or rad].
        test_sigma: ``(P,)`` the sigmas a change is judged in (the prior's, :attr:`Prior.sigma`); inf: not asked.
        rows: the rows the fit had.
    """
    prec = torch.where(torch.isfinite(fit_sigma), fit_sigma.clamp(min=1e-300) ** -2, torch.zeros_like(fit_sigma))
    Nd = N - torch.diag(prec)
    Q = _cofactor(N)
    share = (1.0 - Q.diagonal() * prec).clamp(0.0, 1.0)
    asked = torch.isfinite(test_sigma)
    untold = []
    for j in range(len(names)):
        if not bool(asked[j]) or float(share[j]) * k > threshold:
            continue
        ratio = (k * float(test_sigma[j]) * Q[:, j].abs() * prec[j] / test_sigma).nan_to_num(0.0)
        ratio[j] = 0.0
        absorbed = [names[i] for i in torch.argsort(ratio, descending=True).tolist()[:4] if float(ratio[i]) >= 1.0]
        r = float(share[j])
        untold.append({"name": names[j], "share": r, "detectable_from": threshold / r if r > 0 else None})
        untold[-1]["absorbed_by"] = absorbed
    untold.sort(key=lambda u: u["share"])
    for u in untold:  # the rows like these that tell this one
        t = _rows_factor(Nd, prec, torch.tensor([names.index(u["name"])], device=Nd.device), threshold / k)
        u["rows_needed"] = None if t is None else math.ceil(rows * t)
    idx = torch.tensor([names.index(u["name"]) for u in untold], dtype=torch.long, device=Nd.device)
    need = _rows_factor(Nd, prec, idx, threshold / k) if untold else None
    rows_needed = None if need is None else math.ceil(rows * need)
    return Detectability(tuple(names), tuple(share.tolist()), tuple(untold), k, threshold, rows, rows_needed)


def _cofactor(N: Tensor) -> Tensor:
    """``N^-1`` through the Cholesky factor of the Jacobi-scaled ``N``."""
    s = N.diagonal().clamp(min=1e-300).rsqrt()
    return torch.cholesky_inverse(torch.linalg.cholesky(N * s[:, None] * s[None, :])) * s[:, None] * s[None, :]


def _rows_factor(Nd: Tensor, prec: Tensor, idx: Tensor, need: float, most: float = 1e3) -> float | None:
    """The smallest ``t`` for which ``t Nd + diag(prec)`` gives every parameter ``idx`` a share above ``need``
    (bisection on ``log t``; the share grows with ``t``), or None where ``t = most`` does not."""

    def tells(t: float) -> bool:
        sh = 1.0 - _cofactor(t * Nd + torch.diag(prec)).diagonal()[idx] * prec[idx]
        return bool((sh > need).all())

    if not tells(most):
        return None
    lo, hi = 0.0, math.log(most)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if tells(math.exp(mid)) else (mid, hi)
    return math.exp(hi)
