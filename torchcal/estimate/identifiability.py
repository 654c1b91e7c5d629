"""Which parameters the data can separate, decided from the Jacobian at the data's poses.

Method: normalise every column of the Jacobian to unit length (so metres and radians
compare), then walk the parameters in order of preference and keep a parameter when its
column is independent of the columns kept so far: the sine of the angle between the column
and their span (the norm of its component orthogonal to them) must exceed ``tol``. The
others are held fixed at their current values. This keeps a maximal identifiable set and,
among the possible ones, the one the preference order asks for.

The default preference keeps the instrument pose, then the lever arm, then the robot's
geometry from base to tip, as Horvath & Neuner (2024, Sec. 2.2.3) do: for a UR5 that fixes
``d1, d3, d4, d6, theta1, theta6, alpha6, a6`` in favour of the instrument and lever arm.

Tolerance: ``tol = 1e-6`` by default. Exact dependencies come out at 1e-16..1e-12 (round-off),
so anything below 1e-6 is structural, not a matter of measurement design. Parameters that are
independent but weakly determined are kept and show up through their standard deviations
and correlations in the report.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

Tensor = torch.Tensor

DEFAULT_TOL = 1e-6


@dataclass
class Identifiability:
    names: list[str]
    free: Tensor  # (P,) bool: kept
    independence: Tensor  # (P,) sine of the angle to the span of the earlier kept columns (0 for no effect)
    fixed: list[dict] = field(default_factory=list)
    groups: list[list[str]] = field(default_factory=list)
    singular_values: Tensor | None = None  # of the normalised Jacobian, all candidates
    tol: float = DEFAULT_TOL

    @property
    def rank(self) -> int:
        return int(self.free.sum())

    def to_dict(self) -> dict:
        sv = self.singular_values
        return {
            "method": "column-normalised Jacobian; greedy independence test in preference order",
            "tol": self.tol,
            "n_candidates": len(self.names),
            "rank": self.rank,
            "fixed": self.fixed,
            "dependent_groups": self.groups,
            "condition_number": None if sv is None or float(sv[self.rank - 1]) == 0 else
            float(sv[0] / sv[self.rank - 1]),
        }


def analyse(J: Tensor, names: list[str], order: list[int] | None = None, tol: float = DEFAULT_TOL) -> Identifiability:
    """Decide which columns of ``J (n, P)`` to keep (module docstring).

    Args:
        J: Jacobian of the (whitened) residuals with respect to the candidate parameters.
        names: the P parameter names.
        order: preference order (indices, most wanted first); default the given order.
        tol: independence threshold.
    """
    n, P = J.shape
    order = list(range(P)) if order is None else list(order)
    norms = J.norm(dim=0)
    scale = float(norms.max()) if P else 1.0
    Jn = J / norms.clamp(min=1e-300)
    free = torch.zeros(P, dtype=torch.bool)
    indep = torch.zeros(P, dtype=J.dtype)
    basis = torch.zeros(n, 0, dtype=J.dtype)
    for j in order:
        if float(norms[j]) <= 1e-14 * scale:
            continue  # no effect on the probe at all
        v = Jn[:, j]
        for _ in range(2):  # Gram-Schmidt twice for orthogonality to working precision
            v = v - basis @ (basis.T @ v)
        s = float(v.norm())
        indep[j] = s
        if s > tol:
            free[j] = True
            basis = torch.cat([basis, (v / s)[:, None]], dim=1)

    kept = torch.nonzero(free).flatten()
    fixed, links = [], []
    if len(kept):
        coef = torch.linalg.lstsq(Jn[:, kept], Jn[:, ~free]).solution if int((~free).sum()) else None
    for k, j in enumerate(torch.nonzero(~free).flatten().tolist()):
        if float(norms[j]) <= 1e-14 * scale:
            fixed.append({"name": names[j], "reason": "no effect on the measured positions at these poses",
                          "depends_on": [], "independence": 0.0})
            continue
        c = coef[:, k]
        big = (c.abs() >= 1e-3 * c.abs().max()).nonzero().flatten()
        deps = [names[int(kept[i])] for i in big]
        fixed.append({
            "name": names[j],
            "reason": f"linearly dependent on {', '.join(deps)} at these poses "
                      f"(independence {float(indep[j]):.1e} <= tol {tol:.0e}); held at its current value",
            "depends_on": deps,
            "independence": float(indep[j]),
        })
        links.append([names[j], *deps])
    groups = _merge(links)
    sv = torch.linalg.svdvals(Jn[:, norms > 1e-14 * scale]) if P else None
    return Identifiability(list(names), free, indep, fixed, groups, sv, tol)


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
    """Instrument first, then the lever arm, then everything else in the given order."""
    def rank(i):
        n = names[i]
        return (0 if n.startswith("instrument.") else 1 if n.startswith("tool.") else 2, i)

    return sorted(range(len(names)), key=rank)
