"""Statistics shared by every layer: RMSE, the paired tests, chi-square helpers and the one seeded split.

A leaf module: it imports torch (scipy.stats when a chi-square quantile is asked for) and nothing of torchcal,
so any layer may use it.

The split (:func:`split`) is the only place where the package divides rows into two sets: the held-out
poses of a calibration, the validation poses of the closed loop and of the learned stage, the early-stopping
poses of the correction network. Each use draws from its own named stream (:class:`Stream`), so the sets
are reproducible from the run's seed and independent of each other. Rows that revisit a joint
configuration (every joint within ``group_tol`` rad of another row's) form a group that goes wholly to one
side: otherwise a model that remembers a configuration is judged on a second visit to it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import torch

Tensor = torch.Tensor

#: default tolerance [rad] under which two rows' joints count as the same configuration (every joint)
GROUP_TOL = 1e-3


def rmse(e: Tensor) -> float:
    """Root mean square of per-row errors ``(N,)`` (NaN for none), in their unit."""
    return float(e.square().mean().sqrt()) if len(e) else float("nan")


def normal_sf(z: float) -> float:
    """Upper tail ``P(Z > z)`` of the standard normal distribution."""
    return 0.5 * math.erfc(z / math.sqrt(2.0))


@dataclass(frozen=True)
class PairedTest:
    """The result of a one-sided paired test that one set of per-row errors is smaller than another.

    Attributes:
        z: the test statistic (standard normal under 'no improvement'); corrected for autocorrelation where
            the rows were ordered.
        p_value: its upper tail, ``P(Z > z)``.
        n: the number of pairs.
        lag1_autocorrelation: ``rho`` of the differences, clamped to [0, 0.99]; None where not corrected.
        z_uncorrected: the statistic before the correction; None where not corrected.
    """

    z: float
    p_value: float
    n: int
    lag1_autocorrelation: float | None = None
    z_uncorrected: float | None = None

    def to_dict(self) -> dict:
        """The fields a report writes: ``z``, ``p_value`` and ``n`` (the correction is in the z it gives)."""
        return {"z": self.z, "p_value": self.p_value, "n": self.n}


def paired_improvement(e_before: Tensor, e_after: Tensor) -> PairedTest:
    """One-sided paired test that ``e_after`` (per-pose errors) is smaller than ``e_before``.

    Statistic: mean of ``e_before^2 - e_after^2`` over its standard error; with many poses it is
    close to standard normal under 'no improvement'.
    """
    d = e_before.square() - e_after.square()
    n = len(d)
    se = float(d.std(unbiased=True)) / math.sqrt(n) if n > 1 else float("inf")
    z = float(d.mean()) / se if se > 0 else (float("inf") if float(d.mean()) > 0 else 0.0)
    return PairedTest(z, normal_sf(z), n)


#: the fewest ordered pairs whose lag-one autocorrelation :func:`paired_test` estimates: with fewer, the lag-one
#: sum has at most two terms, which estimate no correlation, and the plain test stands
MIN_AUTOCORRELATION_PAIRS = 4


def paired_test(e_before: Tensor, e_after: Tensor, ordered: bool) -> PairedTest:
    """One-sided paired test that ``e_after`` is smaller (:func:`paired_improvement`).

    With ``ordered`` samples (a trajectory: neighbours share their error) the differences are
    autocorrelated and the plain test is overconfident; the standard error is then inflated by
    ``sqrt((1 + rho) / (1 - rho))``, the AR(1) variance factor of a mean, with ``rho`` the lag-one
    autocorrelation of the differences (clamped to [0, 0.99]).
    """
    test = paired_improvement(e_before, e_after)
    if not ordered or len(e_before) < MIN_AUTOCORRELATION_PAIRS:
        return test
    d = e_before.square() - e_after.square()
    d = d - d.mean()
    rho = float((d[1:] * d[:-1]).sum() / d.square().sum().clamp(min=1e-300))
    rho = min(max(rho, 0.0), 0.99)
    z = test.z / math.sqrt((1 + rho) / (1 - rho))
    return PairedTest(z, normal_sf(z), test.n, lag1_autocorrelation=rho, z_uncorrected=test.z)


def chi2_quantile(p: float, dof: int) -> float:
    """Quantile of the chi-square distribution with ``dof`` degrees of freedom (exact, scipy.stats)."""
    if dof <= 0:
        return float("nan")
    from scipy.stats import chi2  # imported here: scipy costs import time that most commands never need

    return float(chi2.ppf(p, dof))


def chi2_sf_log10(x: float, k: int) -> tuple[float, float]:
    """Upper tail ``P(chi2_k > x)`` and its log10, the latter valid far into the tail where the former underflows.

    ``k`` may be fractional (a scaled chi-square's dof). The tail is the regularised upper incomplete gamma
    function ``Q(k/2, x/2)`` in torch (Cephes' algorithm, as scipy's ``chi2.sf``; they agree to about 1e-13
    relative): the score tests call this in every round, and scipy.stats costs half a second to import.
    """
    p = float(
        torch.special.gammaincc(torch.tensor(0.5 * k, dtype=torch.float64), torch.tensor(0.5 * x, dtype=torch.float64))
    )
    if p > 1e-280:
        return p, math.log10(p)
    # the tail underflows with the tail: the leading terms of the asymptotic series of the upper incomplete
    # gamma function, ln Gamma(a, y) ~ (a - 1) ln y - y + ln(1 + (a - 1) / y), over Gamma(a)
    a, y = 0.5 * k, 0.5 * x
    ln = (a - 1) * math.log(y) - y - math.lgamma(a) + math.log1p((a - 1) / y)
    return p, ln / math.log(10.0)


# --------------------------------------------------------------------------- the split
class Stream(IntEnum):
    """The split's random streams: the seed of a use is the run's seed plus its stream."""

    HOLDOUT = 0  #: the calibration's held-out poses
    CORRECTION_NET = 1  #: early-stopping poses of the correction network (pcm, kinematic+ann); its init follows
    VALIDATION = 2  #: validation poses of the closed loop and of the learned stage
    NETWORK_INIT = 3  #: initial weights of a correction network (not a split; listed so no stream is reused)


@dataclass(frozen=True)
class Split:
    """Two disjoint sets of row indices into the rows that were split.

    Attributes:
        keep: ``(N - K,)`` indices of the rows fitted on.
        held: ``(K,)`` indices of the rows held out (validation or test).
        merged_groups: groups of two or more rows (revisits of one configuration) kept on one side.
        merged_rows: rows in those groups.
    """

    keep: Tensor
    held: Tensor
    merged_groups: int = 0
    merged_rows: int = 0

    def __iter__(self):  # ``keep, held = split(...)``
        return iter((self.keep, self.held))

    def to_dict(self) -> dict:
        return {"merged_groups": self.merged_groups, "merged_rows": self.merged_rows}


def revisit_groups(q: Tensor, tol: float = GROUP_TOL) -> Tensor:
    """Group label per row ``(N,)``: rows whose joints ``q (N, dof)`` [rad] all agree within ``tol`` share one.

    Labels are transitive (a chain of close rows is one group) and number the groups in the order of their
    first row, so that with no revisits the label of row ``i`` is ``i``. Cost: a sort on the first joint and a
    sweep over the rows within ``tol`` of each other in that joint.
    """
    n = len(q)
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if n > 1 and tol > 0:
        order = torch.argsort(q[:, 0])
        qs = q[order]
        first = qs[:, 0].contiguous()
        # the rows j > i in sorted order with first[j] - first[i] <= tol: compare only those
        ends = torch.searchsorted(first, first + tol, right=True)
        for i in range(n):
            if int(ends[i]) <= i + 1:
                continue
            close = (qs[i + 1 : int(ends[i])] - qs[i]).abs().amax(dim=-1) <= tol
            for j in torch.nonzero(close).flatten().tolist():
                a, b = root(int(order[i])), root(int(order[i + 1 + j]))
                if a != b:
                    parent[max(a, b)] = min(a, b)
    roots = [root(i) for i in range(n)]
    label, out = {}, []
    for r in roots:
        out.append(label.setdefault(r, len(label)))
    return torch.tensor(out, dtype=torch.long)


def holdout_count(n: int, fraction: float, *, minimum: int = 1) -> int:
    """How many of ``n`` rows a split holds out: ``fraction * n`` rounded to the nearest, at least ``minimum``."""
    return max(minimum, int(round(fraction * n)))


#: share of the training rows that validate a choice: the closed loop's candidates, the learned stage, the
#: correction network's early stopping and the integrated method's block at the end of a path
VALIDATION_FRACTION = 0.2
#: the fewest validation rows: the paired test that judges on them has no standard error worth the name below
#: three differences
MIN_VALIDATION = 3


def validation_count(n: int) -> int:
    """How many of ``n`` training rows validate (the one rule of every validation split): :data:`VALIDATION_FRACTION`
    of them rounded to the nearest, at least :data:`MIN_VALIDATION`."""
    return holdout_count(n, VALIDATION_FRACTION, minimum=MIN_VALIDATION)


def split(
    n: int,
    held: int,
    *,
    seed: int | None = None,
    generator: torch.Generator | None = None,
    last: bool = False,
    q: Tensor | None = None,
    group_tol: float = GROUP_TOL,
    sort: bool = True,
) -> Split:
    """Split ``n`` rows into ``n - held`` kept and ``held`` held-out ones (module docstring).

    Args:
        n: number of rows.
        held: rows to hold out (:func:`holdout_count`); with revisit groups the held-out side takes whole
            groups, in random order, until it has at least ``held`` rows.
        seed: seed of a fresh generator (the run's seed plus a :class:`Stream`), or
        generator: a generator to draw from (it advances; for uses that draw more afterwards).
        last: hold out the last ``held`` rows (a trajectory: the future of what is fitted); no randomness.
        q: ``(n, dof)`` joint positions [rad] to group revisits by; None: every row is its own group.
        group_tol: joint tolerance [rad] of a revisit (:func:`revisit_groups`).
        sort: return each side in row order (else in the random order drawn).

    With no revisits the split is the plain one: a random permutation of the rows, the first ``held`` held out.
    """
    if last:
        idx = torch.arange(n)
        return Split(idx[: n - held], idx[n - held :])
    if generator is None:
        generator = torch.Generator().manual_seed(int(seed or 0))
    labels = revisit_groups(q, group_tol) if q is not None else None
    n_groups = int(labels.max()) + 1 if labels is not None and n else n
    if labels is None or n_groups == n:
        perm = torch.randperm(n, generator=generator)
        keep, out = perm[held:], perm[:held]
        merged = (0, 0)
    else:
        sizes = torch.bincount(labels, minlength=n_groups)
        gperm = torch.randperm(n_groups, generator=generator)
        cut = int(torch.searchsorted(torch.cumsum(sizes[gperm], 0), torch.tensor(held))) + 1
        held_groups = torch.zeros(n_groups, dtype=torch.bool)
        held_groups[gperm[:cut]] = True
        # rows in the order of their group's draw, so that ``sort=False`` still gives a random order
        rank = torch.empty(n_groups, dtype=torch.long)
        rank[gperm] = torch.arange(n_groups)
        rows = torch.argsort(rank[labels], stable=True)
        out, keep = rows[held_groups[labels[rows]]], rows[~held_groups[labels[rows]]]
        big = sizes > 1
        merged = (int(big.sum()), int(sizes[big].sum()))
    if sort:
        keep, out = torch.sort(keep).values, torch.sort(out).values
    return Split(keep, out, *merged)


#: the guard's edge: a held-out pose with a joint beyond this quantile of the training poses' (either side)
HOLDOUT_EDGE = 0.025


def first_alike(rows: Tensor) -> Tensor:
    """``(N,)``: for each row of ``rows (N, k)`` the index of the first row equal to it to the last digit (its own
    where none before it is)."""
    _, inverse = torch.unique(rows, dim=0, return_inverse=True)
    first = torch.full((int(inverse.max()) + 1 if len(inverse) else 0,), len(inverse), dtype=torch.long)
    first = first.scatter_reduce(0, inverse.cpu(), torch.arange(len(inverse)), reduce="amin")
    return first[inverse.cpu()]


def at_edges(q_train: Tensor, q_hold: Tensor, share: float = HOLDOUT_EDGE) -> Tensor:
    """Which poses ``q_hold`` ``(M,)`` lie at the edges of the poses ``q_train``'s joint ranges: some joint below its
    ``share`` quantile or above its ``1 - share`` quantile in ``q_train`` (or beyond their range)."""
    if len(q_hold) == 0 or len(q_train) == 0:
        return torch.zeros(len(q_hold), dtype=torch.bool, device=q_hold.device)
    lo = torch.quantile(q_train, share, dim=0)
    hi = torch.quantile(q_train, 1.0 - share, dim=0)
    return ((q_hold < lo) | (q_hold > hi)).any(dim=1)
